"""Foreign calibrations (SLStudio, cv2.stereoCalibrate) read into rigs, and their bad files refused."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.cli.main import main
from services.errors import InputError
from services.formats.foreign_rig import import_rig
from services.formats.rig import load_rig, rig_to_json

SLSTUDIO_XML = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "slstudio" / "calibration" / \
    "calibration.xml"  # shared/ beside the clone
_R = cv2.Rodrigues(np.array([0.05, -0.3, 0.02]))[0]
_T = np.array([[120.0], [-3.5], [10.0]])


def _write_storage(path: Path, entries: dict) -> Path:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in entries.items():
        storage.write(key, value)
    storage.release()
    return path


def _stereo_entries(**overrides):
    entries = {"K1": np.array([[800.0, 0, 320], [0, 805, 240], [0, 0, 1]]), "D1": np.array([[-0.1, 0.02, 0, 0, 0]]),
               "K2": np.array([[400.0, 0, 160], [0, 400, 128], [0, 0, 1]]), "D2": np.array([[-0.2, 0.1, 0, 0, 0]]),
               "R": _R, "T": _T, "imageSize1": np.array([[640.0, 480.0]]), "imageSize2": np.array([[320.0, 256.0]])}
    entries.update(overrides)
    return {key: value for key, value in entries.items() if value is not None}


def test_slstudio_calibration_xml_is_read_with_its_conventions():
    assert SLSTUDIO_XML.is_file(), f"the real SLStudio calibration {SLSTUDIO_XML} is missing"
    rig = import_rig(SLSTUDIO_XML, "slstudio")
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    assert (camera.kind, camera.size, projector.kind, projector.size) == ("camera", (1688, 1352), "projector",
                                                                          (1824, 1140))
    np.testing.assert_allclose(camera.K, [[2195.12036, 0, 843.5], [0, 2195.12036, 675.5], [0, 0, 1]], rtol=1e-8)
    np.testing.assert_allclose(camera.dist, [-5.80352657e-02, 0, 0, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(projector.K[0], [2601.52563, 0, 866.541504], rtol=1e-8)
    np.testing.assert_allclose(projector.t, [-145.282562, -36.4983406, 67.9231644], rtol=1e-6)
    # the camera is the world; Rp maps camera to projector coordinates, so Rp itself is the projector's R
    np.testing.assert_array_equal(camera.R, np.eye(3))
    np.testing.assert_allclose(projector.R[0], [0.964402318, -0.120346159, 0.235467508], atol=1e-7)
    np.testing.assert_allclose(projector.R @ projector.R.T, np.eye(3), atol=1e-12)


@pytest.mark.parametrize("suffix", ["yml", "xml"])
def test_opencv_stereo_file_round_trips_through_the_cli(tmp_path, suffix, capsys):
    source = _write_storage(tmp_path / f"stereo.{suffix}", _stereo_entries())
    out = tmp_path / "rig.json"
    assert main(["rig", "import", "--format", "opencv-stereo", str(source), "--out", str(out),
                 "--names", "visible", "ir", "--kinds", "camera", "thermal"]) == 0
    rig = load_rig(out)
    visible, ir = rig.devices["visible"], rig.devices["ir"]
    assert (visible.kind, visible.size, ir.kind, ir.size) == ("camera", (640, 480), "thermal", (320, 256))
    np.testing.assert_allclose(ir.R, _R, atol=1e-12)
    np.testing.assert_allclose(ir.t, _T.ravel())
    np.testing.assert_allclose(ir.dist, [-0.2, 0.1, 0, 0, 0])
    # x_2 = R x_1 + T: the second device's centre in the first's frame is -R^T T
    np.testing.assert_allclose(-ir.R.T @ ir.t, -_R.T @ _T.ravel())
    assert "baseline" in capsys.readouterr().out


def test_opencv_sample_names_and_sizes_from_the_command_line(tmp_path):
    entries = _stereo_entries(imageSize1=None, imageSize2=None)
    entries["M1"], entries["M2"] = entries.pop("K1"), entries.pop("K2")
    source = _write_storage(tmp_path / "intrinsics.yml", entries)
    with pytest.raises(InputError, match=r"intrinsics.yml: no image size for camera"):
        import_rig(source, "opencv-stereo")
    rig = import_rig(source, "opencv-stereo", sizes=((640, 480), (1024, 768)))
    assert rig.devices["projector"].size == (1024, 768)
    assert rig.devices["camera"].K[1, 1] == 805


@pytest.mark.parametrize("overrides, message", [
    ({"K2": None}, r"stereo.yml: K2: missing"),
    ({"T": None}, r"stereo.yml: T: missing"),
    ({"K1": np.eye(3)[:2]}, r"stereo.yml: K1: must be a 3x3 matrix; got 2x3"),
    ({"T": np.array([[1.0], [2.0]])}, r"stereo.yml: T: must be a 3x1 matrix; got 2x1"),
    ({"D1": np.array([[0.1, 0.2, 0.3]])}, r"stereo.yml: D1: must be a vector of"),
    ({"R": np.array([[1.0, 0, 0], [0, 1, 0], [0, 0.2, 1]])}, r"stereo.yml: R: not a rotation matrix"),
    ({"R": np.diag([1.0, 1.0, -1.0])}, r"stereo.yml: R: not a rotation matrix .*det = -1"),
    ({"K1": np.array([[800.0, 0, 320], [0, -805, 240], [0, 0, 1]])}, r"stereo.yml: K1: focal lengths must be positive"),
    ({"K1": np.array([[800.0, 2, 320], [0, 805, 240], [0, 0, 1]])}, r"stereo.yml: K1: has skew"),
    ({"T": np.array([[np.nan], [0.0], [0.0]])}, r"stereo.yml: T: contains a non-finite value"),
])
def test_bad_stereo_files_get_one_line_naming_file_and_key(tmp_path, overrides, message, capsys):
    source = _write_storage(tmp_path / "stereo.yml", _stereo_entries(**overrides))
    with pytest.raises(InputError, match=message):
        import_rig(source, "opencv-stereo")
    assert main(["rig", "import", "--format", "opencv-stereo", str(source), "--out", str(tmp_path / "rig.json")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("thermofield: error: ") and error.count("\n") == 1 and "stereo.yml" in error
    assert not (tmp_path / "rig.json").exists()


def test_bad_slstudio_files(tmp_path):
    with pytest.raises(InputError, match=r"missing.xml: calibration file does not exist"):
        import_rig(tmp_path / "missing.xml", "slstudio")
    garbage = tmp_path / "garbage.xml"
    garbage.write_text("not a calibration <<\n")
    with pytest.raises(InputError, match=r"garbage.xml: not an OpenCV FileStorage"):
        import_rig(garbage, "slstudio")
    entries = {"Kc": np.diag([2000.0, 2000.0, 1.0]), "kc": np.zeros((5, 1)), "Kp": np.diag([2500.0, 2500.0, 1.0]),
               "kp": np.zeros((5, 1)), "Rp": np.eye(3), "Tp": np.array([[-150.0], [0.0], [60.0]]),
               "frameWidth": 1688, "frameHeight": 1352, "screenResX": 1824}
    partial = _write_storage(tmp_path / "calibration.xml", entries)
    with pytest.raises(InputError, match=r"calibration.xml: screenResY: missing"):
        import_rig(partial, "slstudio")
    _write_storage(partial, {**entries, "screenResY": 1140, "Kp": np.eye(3)[:, :2]})
    with pytest.raises(InputError, match=r"calibration.xml: Kp: must be a 3x3 matrix; got 3x2"):
        import_rig(partial, "slstudio")
    _write_storage(partial, {**entries, "screenResY": 1140})
    rig = import_rig(partial, "slstudio", names=("cam", "proj"))
    assert json.loads(rig_to_json(rig))["devices"]["proj"]["t"] == [-150.0, 0.0, 60.0]
    with pytest.raises(InputError, match="different names"):
        import_rig(partial, "slstudio", names=("same", "same"))
