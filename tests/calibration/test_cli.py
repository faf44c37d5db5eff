import json
import shutil

import cv2
import numpy as np
import pytest

from services.cli.main import main
from services.formats.board import parse_board
from services.formats.calibration import CameraCalibrationFile, load_camera_calibration, save_camera_calibration
from services.formats.images import write_png
from services.formats.rig import Rig, load_rig, save_rig
from services.geometry.camera_model import CameraModel

from .simulated_rig import CAMERA_DIST, CAMERA_K, CAMERA_SIZE, THERMAL_DIST, THERMAL_FROM_CAMERA, THERMAL_K, THERMAL_SIZE

pytestmark = pytest.mark.integration

REPORT_SUFFIXES = ("_residual_bars.png", "_residual_vectors.png", "_coverage.png")


@pytest.fixture()
def opencv_board_file(tmp_path):
    path = tmp_path / "board.json"
    path.write_text('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 1.0}')
    return path


@pytest.fixture()
def left_dir(tmp_path, opencv_left_images):
    directory = tmp_path / "left"
    directory.mkdir()
    for path in opencv_left_images:
        shutil.copy(path, directory / path.name)
    return directory


def test_calibrate_camera_on_opencv_images_writes_the_file_and_its_report(tmp_path, opencv_board_file, left_dir):
    out = tmp_path / "left.json"
    assert main(["calibrate", "camera", "--board", str(opencv_board_file), "--images", str(left_dir),
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert (result["width"], result["height"]) == (640, 480)
    assert result["rms_px"] <= 0.196
    assert len(result["views"]) == 13 and result["rejected"] == []
    assert set(result["std"]) == {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}
    assert all(len(view["pose_std"]) == 6 for view in result["views"])
    # the image corners hold no feature (docs/calibration.md): the lens is extrapolated there, and the file says so
    assert len(result["poorly_determined"]) == 1
    assert result["poorly_determined"][0].startswith("distortion poorly determined")
    for suffix in REPORT_SUFFIXES:
        figure = cv2.imread(str(out.parent / f"left{suffix}"))
        assert figure is not None and figure.shape[0] > 200


def _expect_error(capsys, argv, *fragments):
    assert main(argv) == 2
    message = capsys.readouterr().err
    for fragment in fragments:
        assert fragment in message
    assert "Traceback" not in message
    return message


def test_images_without_a_board_are_each_listed(tmp_path, capsys, opencv_board_file):
    images = tmp_path / "blank"
    images.mkdir()
    rng = np.random.default_rng(0)
    for index in range(3):
        write_png(images / f"noise{index}.png", rng.integers(0, 255, (120, 160), dtype=np.uint8))
    out = tmp_path / "cam.json"
    _expect_error(capsys, ["calibrate", "camera", "--board", str(opencv_board_file), "--images", str(images),
                           "--out", str(out)], "3 of 3 images", "noise0.png: no chessboard", "noise2.png")
    assert not out.exists() and list(tmp_path.glob("cam*")) == []


def test_a_board_spec_that_does_not_match_is_reported(tmp_path, capsys, left_dir):
    board = tmp_path / "board.json"
    board.write_text('{"type": "chessboard", "inner_corners": [8, 6], "square_mm": 1.0}')
    for path in sorted(left_dir.iterdir())[3:]:
        path.unlink()
    _expect_error(capsys, ["calibrate", "camera", "--board", str(board), "--images", str(left_dir),
                           "--out", str(tmp_path / "cam.json")], "8x6", "left01.jpg", "left03.jpg")


def test_corrupt_and_mixed_size_images_are_reported(tmp_path, capsys, opencv_board_file, left_dir):
    (left_dir / "zz_corrupt.png").write_bytes(b"not a png")
    write_png(left_dir / "zz_small.png", np.zeros((100, 100), np.uint8))
    _expect_error(capsys, ["calibrate", "camera", "--board", str(opencv_board_file), "--images", str(left_dir),
                           "--out", str(tmp_path / "cam.json")],
                  "2 of 15 images", "zz_corrupt.png: cannot read", "zz_small.png: image is 100x100")


def test_fewer_than_three_images_are_refused(tmp_path, capsys, opencv_board_file, left_dir):
    for path in sorted(left_dir.iterdir())[2:]:
        path.unlink()
    _expect_error(capsys, ["calibrate", "camera", "--board", str(opencv_board_file), "--images", str(left_dir),
                           "--out", str(tmp_path / "cam.json")], "2 images", "at least 3")


def test_a_bad_board_file_is_named(tmp_path, capsys, left_dir):
    board = tmp_path / "board.json"
    board.write_text('{"type": "chessboard", "inner_corners": [9, 6]}')
    _expect_error(capsys, ["calibrate", "camera", "--board", str(board), "--images", str(left_dir),
                           "--out", str(tmp_path / "cam.json")], "board.json", "square_mm")


def test_calibrate_stereo_places_the_thermal_camera_in_the_rig(tmp_path, visible_infrared_pairs):
    board = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 20.0}')
    board_file = tmp_path / "board.json"
    board_file.write_text(board.model_dump_json())
    for name in ("visible", "thermal"):
        (tmp_path / "pairs" / name).mkdir(parents=True)
    for index, (visible, infrared) in enumerate(visible_infrared_pairs):
        write_png(tmp_path / "pairs" / "visible" / f"pair{index:02d}.png", visible)
        write_png(tmp_path / "pairs" / "thermal" / f"pair{index:02d}.png", infrared)
    camera_R, camera_t = cv2.Rodrigues(np.array([0.0, 0.35, 0.0]))[0], np.array([-140.0, 0.0, 50.0])
    rig = Rig(devices={"visible": CameraModel(kind="camera", width=CAMERA_SIZE[0], height=CAMERA_SIZE[1],
                                         K=CAMERA_K.tolist(), dist=CAMERA_DIST.tolist(), R=camera_R.tolist(),
                                         t=camera_t.tolist())})
    save_rig(rig, tmp_path / "rig.json")
    intrinsics = CameraCalibrationFile(name="thermal", kind="thermal", width=THERMAL_SIZE[0], height=THERMAL_SIZE[1],
                                       K=THERMAL_K.tolist(), dist=THERMAL_DIST.tolist(), distortion_model="radial",
                                       rms_px=0.05, std={}, board=board, views=[], rejected=[])
    save_camera_calibration(intrinsics, tmp_path / "thermal.json")
    assert main(["calibrate", "stereo", "--board", str(board_file), "--pairs", str(tmp_path / "pairs"),
                 "--rig", str(tmp_path / "rig.json"), "--device", "thermal", "--intrinsics",
                 str(tmp_path / "thermal.json"), "--out", str(tmp_path / "rig2.json")]) == 0
    thermal = load_rig(tmp_path / "rig2.json").devices["thermal"]
    R_rel, t_rel = THERMAL_FROM_CAMERA
    np.testing.assert_allclose(thermal.R, R_rel @ camera_R, atol=1e-3)
    np.testing.assert_allclose(thermal.t, R_rel @ camera_t + t_rel, atol=0.5)
    assert thermal.kind == "thermal" and np.array_equal(thermal.K, THERMAL_K)
    report = json.loads((tmp_path / "rig2_stereo_thermal.json").read_text())
    assert report["stereo_rms_px"] < 0.1 and len(report["pairs"]) == len(visible_infrared_pairs)
    assert abs(report["baseline_mm"] - np.linalg.norm(t_rel)) < 0.5


def test_calibrate_stereo_needs_the_device_intrinsics(tmp_path, capsys, opencv_board_file):
    save_rig(Rig(devices={"visible": CameraModel(kind="camera", width=640, height=480,
                                            K=CAMERA_K.tolist())}), tmp_path / "rig.json")
    _expect_error(capsys, ["calibrate", "stereo", "--board", str(opencv_board_file), "--pairs", str(tmp_path),
                           "--rig", str(tmp_path / "rig.json"), "--device", "thermal", "--out",
                           str(tmp_path / "out.json")], "no device 'thermal'", "--intrinsics")


def test_calibrate_camera_on_simulated_infrared_frames(tmp_path, visible_infrared_pairs, chessboard_9x6):
    (tmp_path / "board.json").write_text(chessboard_9x6.model_dump_json())
    images = tmp_path / "thermal"
    images.mkdir()
    for index, (_, infrared) in enumerate(visible_infrared_pairs):
        write_png(images / f"ir{index:02d}.png", infrared.astype(np.uint16) * 257)  # as a 16-bit camera writes
    out = tmp_path / "thermal.json"
    assert main(["calibrate", "camera", "--board", str(tmp_path / "board.json"), "--images", str(images), "--out",
                 str(out), "--kind", "thermal", "--name", "ir", "--distortion", "radial"]) == 0
    result = json.loads(out.read_text())
    assert result["kind"] == "thermal" and result["name"] == "ir" and len(result["dist"]) == 5
    assert len(result["views"]) + len(result["rejected"]) == len(visible_infrared_pairs)
    K = np.asarray(result["K"])
    assert np.abs(np.diag(K)[:2] / np.diag(THERMAL_K)[:2] - 1).max() < 5e-3
    assert result["std"]["fx"] > 0 and "p1" not in result["std"]


def test_calibrate_camera_chooses_the_lens_model_and_says_why(tmp_path, capsys, visible_infrared_pairs, chessboard_9x6):
    (tmp_path / "board.json").write_text(chessboard_9x6.model_dump_json())
    images = tmp_path / "thermal"
    images.mkdir()
    for index, (_, infrared) in enumerate(visible_infrared_pairs):
        write_png(images / f"ir{index:02d}.png", infrared)
    out = tmp_path / "thermal.json"
    assert main(["calibrate", "camera", "--board", str(tmp_path / "board.json"), "--images", str(images), "--out",
                 str(out), "--kind", "thermal", "--distortion", "auto"]) == 0
    result = load_camera_calibration(out)
    candidates = {c.model: c for c in result.model_selection.candidates}
    assert set(candidates) == {"none", "radial", "standard", "rational"}
    assert min(candidates.values(), key=lambda c: c.bic).model == result.distortion_model
    assert result.model_selection.reason.startswith(result.distortion_model)
    assert f"lens model {result.distortion_model}" in capsys.readouterr().out


def test_nearly_flat_views_leave_the_focal_length_poorly_determined_in_the_file_and_the_output(tmp_path, capsys, chessboard_9x6):
    from services.simulation.boards import render_board

    from .simulated_rig import board_poses

    (tmp_path / "board.json").write_text(chessboard_9x6.model_dump_json())
    images = tmp_path / "thermal"
    images.mkdir()
    rng = np.random.default_rng(4)
    for index, (R, t) in enumerate(board_poses(chessboard_9x6, 6, 370.0, 3.0)):  # tilted 3 degrees: nearly flat
        write_png(images / f"ir{index:02d}.png", render_board(chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE,
                                                             modality="infrared", blur_sigma=1.0, noise_sigma=2.0,
                                                             supersample=2, rng=rng))
    out = tmp_path / "thermal.json"
    assert main(["calibrate", "camera", "--board", str(tmp_path / "board.json"), "--images", str(images), "--out",
                 str(out), "--kind", "thermal", "--distortion", "radial"]) == 0
    messages = load_camera_calibration(out).poorly_determined
    assert any(m.startswith("focal length poorly determined") for m in messages)
    printed = capsys.readouterr().out
    assert all(f"thermal: {m}" in printed for m in messages)
