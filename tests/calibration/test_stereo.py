import cv2
import numpy as np
import pytest

from services.calibration.camera import calibrate_camera
from services.calibration.corners import detect_board
from services.calibration.stereo import calibrate_stereo
from services.formats.images import read_frame

from .conftest import OPENCV_IMAGES
from .simulated_rig import CAMERA_DIST, CAMERA_K, CAMERA_SIZE, THERMAL_DIST, THERMAL_FROM_CAMERA, THERMAL_K


def test_thermal_pose_is_recovered_from_simulated_visible_infrared_pairs(visible_infrared_pairs, chessboard_9x6):
    objects, first, second = [], [], []
    for visible, infrared in visible_infrared_pairs:
        a, b = detect_board(visible, chessboard_9x6), detect_board(infrared, chessboard_9x6)
        objects.append(chessboard_9x6.object_points())
        first.append(a.image_points)
        second.append(b.image_points)
    result = calibrate_stereo(objects, first, second, (CAMERA_K, CAMERA_DIST), (THERMAL_K, THERMAL_DIST), CAMERA_SIZE)
    R_true, t_true = THERMAL_FROM_CAMERA
    angle_error = np.degrees(np.linalg.norm(cv2.Rodrigues(result.R @ R_true.T)[0]))
    assert angle_error < 0.05
    assert np.linalg.norm(result.t - t_true) < 0.5
    assert abs(result.baseline_mm - np.linalg.norm(t_true)) < 0.5
    assert result.rms < 0.1


def test_opencv_left_right_pairs_give_a_small_stereo_rms(opencv_board):
    sides = {}
    for side in ("left", "right"):
        paths = sorted(OPENCV_IMAGES.glob(f"{side}*.jpg"))
        sides[side] = [detect_board(read_frame(path), opencv_board).image_points for path in paths]
    objects = [opencv_board.object_points()] * len(sides["left"])
    left = calibrate_camera(objects, sides["left"], (640, 480))
    right = calibrate_camera(objects, sides["right"], (640, 480))
    result = calibrate_stereo(objects, sides["left"], sides["right"], (left.K, left.dist), (right.K, right.dist),
                              (640, 480))
    assert result.rms < 0.25  # measured 0.200 px
    assert result.t[0] < 0  # the right camera is to the right: the left origin is at negative x in it
    assert 3.0 < result.baseline_mm < 3.7  # about 3.3 squares


def test_empty_view_lists_are_refused():
    with pytest.raises(ValueError, match="at least one view"):
        calibrate_stereo([], [], [], (np.eye(3), np.zeros(5)), (np.eye(3), np.zeros(5)), (640, 480))
