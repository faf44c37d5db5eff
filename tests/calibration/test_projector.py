import json

import cv2
import numpy as np
import pytest

from services.calibration.corners import detect_board
from services.calibration.projector import calibrate_projector, projector_corners
from services.cli.main import main
from services.formats.calibration import CameraCalibrationFile, save_camera_calibration
from services.formats.images import write_png
from services.formats.rig import load_rig
from services.formats.sequence import save_sequence
from services.geometry.camera import project_points
from services.structured_light.decode import decode

from .simulated_rig import PROJECTOR_CAMERA_DIST, PROJECTOR_CAMERA_K, PROJECTOR_CAMERA_SIZE, projector_beside_camera

pytestmark = pytest.mark.integration


def _corners_of(capture, board):
    sequence, frames, _ = capture
    decoded = decode(frames, sequence)
    lit = np.clip(np.round(decoded.intensity), 0, 255).astype(np.uint8)
    detection = detect_board(lit, board)
    spacing = np.median(np.linalg.norm(np.diff(detection.image_points.reshape(6, 9, 2), axis=1), axis=2))
    corners, found = projector_corners(detection.image_points, decoded.projector_x, decoded.projector_y,
                                       int(spacing / 2), decoded.modulation)
    return detection.image_points, corners, found


def test_projector_corners_and_calibration_meet_the_targets(projector_captures, chessboard_15mm):
    projector = projector_beside_camera()
    objects, camera_points, projector_points = [], [], []
    for capture in projector_captures:
        image_points, corners, found = _corners_of(capture, chessboard_15mm)
        R, t = capture[2]
        truth = project_points(chessboard_15mm.object_points() @ R.T + t, projector.K, projector.dist,
                               projector.R, projector.t)
        assert found.all()
        assert np.sqrt(np.mean(np.sum((corners - truth) ** 2, axis=1))) < 0.15
        objects.append(chessboard_15mm.object_points())
        camera_points.append(image_points)
        projector_points.append(corners)
    result = calibrate_projector(objects, camera_points, projector_points, (PROJECTOR_CAMERA_K, PROJECTOR_CAMERA_DIST),
                                 PROJECTOR_CAMERA_SIZE, projector.size)
    assert result.projector.rms <= 0.3
    assert np.abs(np.diag(result.projector.K)[:2] / np.diag(projector.K)[:2] - 1).max() < 2e-3
    angle = np.degrees(np.linalg.norm(cv2.Rodrigues(result.stereo.R @ projector.R.T)[0]))
    assert angle < 0.2
    assert np.linalg.norm(result.stereo.t - projector.t) < 2.0
    assert result.stereo.rms <= 0.3


def _write_captures(root, captures):
    directories = []
    for index, (sequence, frames, _) in enumerate(captures):
        directory = root / f"pose{index}"
        directory.mkdir(parents=True)
        save_sequence(sequence, directory)
        for frame, image in zip(sequence.frames, frames):
            write_png(directory / frame.file, image)
        directories.append(str(directory))
    return directories


def _write_camera(path, board):
    camera = CameraCalibrationFile(name="visible", kind="camera", width=PROJECTOR_CAMERA_SIZE[0],
                                   height=PROJECTOR_CAMERA_SIZE[1], K=PROJECTOR_CAMERA_K.tolist(),
                                   dist=PROJECTOR_CAMERA_DIST.tolist(), distortion_model="radial", rms_px=0.05,
                                   std={}, board=board, views=[], rejected=[])
    save_camera_calibration(camera, path)


def test_calibrate_projector_command_writes_the_rig_and_its_report(tmp_path, projector_captures, chessboard_15mm):
    (tmp_path / "board.json").write_text(chessboard_15mm.model_dump_json())
    _write_camera(tmp_path / "camera.json", chessboard_15mm)
    captures = _write_captures(tmp_path / "captures", projector_captures)
    out = tmp_path / "rig.json"
    assert main(["calibrate", "projector", "--board", str(tmp_path / "board.json"), "--captures", *captures,
                 "--camera", str(tmp_path / "camera.json"), "--out", str(out)]) == 0
    rig = load_rig(out)
    assert set(rig.devices) == {"visible", "projector"}
    np.testing.assert_allclose(rig.devices["visible"].R, np.eye(3))
    truth = projector_beside_camera()
    assert np.linalg.norm(rig.devices["projector"].t - truth.t) < 2.0
    report = json.loads((tmp_path / "rig_projector.json").read_text())
    assert report["projector_rms_px"] <= 0.3 and report["stereo_rms_px"] <= 0.3
    assert len(report["views"]) == 5 and abs(report["baseline_mm"] - np.linalg.norm(truth.t)) < 2.0


def test_calibrate_projector_needs_three_captures(tmp_path, capsys, chessboard_15mm):
    (tmp_path / "board.json").write_text(chessboard_15mm.model_dump_json())
    _write_camera(tmp_path / "camera.json", chessboard_15mm)
    assert main(["calibrate", "projector", "--board", str(tmp_path / "board.json"), "--captures", str(tmp_path),
                 "--camera", str(tmp_path / "camera.json"), "--out", str(tmp_path / "rig.json")]) == 2
    assert "at least 3" in capsys.readouterr().err
    assert not (tmp_path / "rig.json").exists()


def test_projector_corners_refuses_a_tiny_window():
    with pytest.raises(ValueError, match="half_window"):
        projector_corners(np.zeros((1, 2)), np.zeros((5, 5)), np.zeros((5, 5)), 1)
