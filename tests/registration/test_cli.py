import json

import cv2
import numpy as np
import pytest
import tifffile

from services.cli.main import main
from services.registration.models import corner_error
from tests.registration.conftest import INFRARED_SIZE, scene_pair

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def pair_files(tmp_path_factory):
    directory = tmp_path_factory.mktemp("pair")
    visible, infrared, truth = scene_pair(51)
    cv2.imwrite(str(directory / "visible.png"), visible)
    cv2.imwrite(str(directory / "infrared.png"), infrared)
    return directory, truth


def test_register_writes_the_registration_and_both_pictures(pair_files, capsys):
    directory, truth = pair_files
    out = directory / "REG.json"
    code = main(["register", "--fixed", str(directory / "visible.png"), "--moving", str(directory / "infrared.png"),
                 "--model", "similarity", "--out", str(out), "--overlay", str(directory / "overlay.png"),
                 "--checkerboard", str(directory / "board.png")])
    assert code == 0
    document = json.loads(out.read_text())
    assert set(document) == {"model", "matrix", "mi", "nmi", "bins", "log_base"}
    assert document["model"] == "similarity" and document["bins"] == 32 and document["log_base"] == 2.0
    # the default metric, NGF, is less precise on rendered scenes than NMI (docs/registration.md)
    assert corner_error(truth, np.array(document["matrix"]), *INFRARED_SIZE) < 1.0
    for picture in ("overlay.png", "board.png"):
        image = cv2.imread(str(directory / picture), cv2.IMREAD_UNCHANGED)
        assert image.shape == (768, 1024) and image.dtype == np.uint8
    assert "MI" in capsys.readouterr().out
    assert not list(directory.glob("*.part*"))


def test_register_reads_a_float_tiff_infrared_image(pair_files, tmp_path):
    directory, truth = pair_files
    infrared = cv2.imread(str(directory / "infrared.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) * 0.07
    tifffile.imwrite(tmp_path / "infrared.tif", infrared)
    out = tmp_path / "REG.json"
    code = main(["register", "--fixed", str(directory / "visible.png"), "--moving", str(tmp_path / "infrared.tif"),
                 "--model", "translation", "--max-shift", "10", "--bins", "24", "--log-base", "2.718281828459045",
                 "--out", str(out)])
    assert code == 0
    document = json.loads(out.read_text())
    assert document["model"] == "translation" and document["bins"] == 24


def test_register_leaves_out_the_infrared_pixels_the_mask_marks_as_without_data(pair_files, tmp_path):
    # NMI, which keeps to a pixel with half the image; NGF's half-image precision is test_register.py's
    directory, truth = pair_files
    infrared = cv2.imread(str(directory / "infrared.png"), cv2.IMREAD_UNCHANGED)
    decoy = infrared.copy()  # the left half shows the scene 18 px to the right and 12 px down
    decoy[:, :170] = np.roll(infrared, (12, 18), axis=(0, 1))[:, :170]
    mask = np.full(infrared.shape, 255, np.uint8)
    mask[:, :170] = 0
    cv2.imwrite(str(tmp_path / "decoy.png"), decoy)
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    errors = []
    for masking in ([], ["--moving-mask", str(tmp_path / "mask.png")]):
        out = tmp_path / "REG.json"
        assert main(["register", "--fixed", str(directory / "visible.png"), "--moving", str(tmp_path / "decoy.png"),
                     "--metric", "nmi", "--out", str(out)] + masking) == 0
        errors.append(corner_error(truth, np.array(json.loads(out.read_text())["matrix"]), *INFRARED_SIZE))
    assert errors[0] > 10.0 and errors[1] < 1.0, errors


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"--moving": "missing.png"}, "missing.png: frame file is missing"),
        ({"--moving": "bad.npy"}, "bad.npy: the image must be a 2-D numeric array"),
        ({"--overlay": "overlay.jpg"}, "--overlay"),
        ({"--out": "absent/REG.json"}, "does not exist"),
        ({"--bins": "2"}, "at least 4 histogram bins"),
        ({"--scale": "-1"}, "nominal scale must be positive"),
        ({"--moving-mask": "small_mask.png"}, "small_mask.png: the mask is 100x80 pixels, the infrared image 320x256"),
        ({"--moving-mask": "empty_mask.png"}, "empty_mask.png: the mask is zero everywhere"),
        ({"--moving-mask": "missing_mask.png"}, "missing_mask.png: frame file is missing"),
    ],
)
def test_bad_input_exits_2_with_a_message_and_no_traceback(pair_files, tmp_path, capsys, change, message):
    directory, _ = pair_files
    np.save(tmp_path / "bad.npy", np.zeros((2, 3, 4)))
    cv2.imwrite(str(tmp_path / "small_mask.png"), np.full((80, 100), 255, np.uint8))
    cv2.imwrite(str(tmp_path / "empty_mask.png"), np.zeros((256, 320), np.uint8))
    options = {"--fixed": str(directory / "visible.png"), "--moving": str(directory / "infrared.png"),
               "--out": str(tmp_path / "REG.json")}
    for key, value in change.items():
        options[key] = str(tmp_path / value) if value.endswith((".png", ".npy", ".jpg", ".json")) else value
    code = main(["register"] + [item for pair in options.items() for item in pair])
    error = capsys.readouterr().err
    assert code == 2
    assert message in error and "Traceback" not in error
    assert not (tmp_path / "REG.json").exists()


def test_help_names_the_defaults_and_why(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["register", "--help"])
    assert exit_info.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "(default ngf: chosen on the tuning half of the real TNO pairs" in text
    assert "12% of the infrared image's smaller side" in text
    assert "constant border" in text  # what happens without --moving-mask
