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


def test_predicted_pose_standard_deviations_match_a_monte_carlo_spread():
    rng = np.random.default_rng(3)
    board = np.array([[x * 10.0, y * 10.0, 0.0] for y in range(9) for x in range(13)])
    K1, K2 = np.array([[2000.0, 0, 840], [0, 2000, 675], [0, 0, 1]]), np.array([[2600.0, 0, 900], [0, 2600, 1100],
                                                                               [0, 0, 1]])
    dist = np.zeros(5)
    R = cv2.Rodrigues(np.array([0.15, -0.23, 0.14]))[0]
    t = np.array([-145.0, -36.0, 68.0])
    poses = [(cv2.Rodrigues(np.array([0.3 * np.cos(a), 0.3 * np.sin(a), 0.05]))[0], np.array([-60.0, -40.0, 390.0]))
             for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]
    exact_first = [cv2.projectPoints(board, cv2.Rodrigues(Rb)[0], tb, K1, dist)[0].reshape(-1, 2) for Rb, tb in poses]
    exact_second = [cv2.projectPoints(board, cv2.Rodrigues(R @ Rb)[0], R @ tb + t, K2, dist)[0].reshape(-1, 2)
                    for Rb, tb in poses]
    estimates, predicted = [], []
    for _ in range(40):
        first = [p + rng.normal(0, 0.3, p.shape) for p in exact_first]
        second = [p + rng.normal(0, 0.3, p.shape) for p in exact_second]
        result = calibrate_stereo([board] * len(poses), first, second, (K1, dist), (K2, dist), (1688, 1352))
        estimates.append(np.concatenate([cv2.Rodrigues(result.R)[0].ravel(), result.t]))
        predicted.append(result.pose_std)
    ratio = np.mean(predicted, axis=0) / np.std(estimates, axis=0, ddof=1)
    assert np.all((ratio > 0.65) & (ratio < 1.5)), ratio
