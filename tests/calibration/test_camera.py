import cv2
import numpy as np
import pytest

from services.calibration.camera import calibrate_camera, locate_camera
from services.calibration.corners import detect_board
from services.formats.images import read_frame
from services.geometry.camera import project_points
from services.simulation.boards import render_board

from .simulated_rig import THERMAL_DIST, THERMAL_K, THERMAL_SIZE, board_poses, project

pytestmark = pytest.mark.integration

OPENCV_PUBLISHED_RMS = 0.196


@pytest.fixture(scope="module")
def opencv_left_detections(opencv_left_images, opencv_board):
    return [detect_board(read_frame(path), opencv_board) for path in opencv_left_images]


def test_opencv_left_images_beat_opencvs_published_rms(opencv_left_detections, opencv_board):
    assert all(d is not None for d in opencv_left_detections)
    result = calibrate_camera([opencv_board.object_points()] * 13, [d.image_points for d in opencv_left_detections],
                              (640, 480))
    assert result.rms <= OPENCV_PUBLISHED_RMS
    assert result.rejected == []
    # OpenCV's published intrinsics for these images, within three of our standard deviations
    for name, value, index in (("fx", 532.81, (0, 0)), ("fy", 532.93, (1, 1)), ("cx", 342.50, (0, 2)),
                               ("cy", 233.89, (1, 2))):
        assert abs(result.K[index] - value) < 3 * result.std[name], name


def test_predicted_standard_deviations_match_a_monte_carlo_spread(chessboard_9x6):
    K = np.array([[800.0, 0.0, 330.0], [0.0, 790.0, 235.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.15, 0.08, 0.0005, -0.0003, 0.0])
    poses = board_poses(chessboard_9x6, 8, 450.0, 30.0)
    truth = [project(chessboard_9x6, K, dist, R, t) for R, t in poses]
    objects = [chessboard_9x6.object_points()] * len(poses)
    rng = np.random.default_rng(7)
    estimates, predicted, reported = [], [], []
    for _ in range(60):
        noisy = [points + rng.normal(0.0, 0.2, points.shape) for points in truth]
        result = calibrate_camera(objects, noisy, (640, 480), distortion="radial", reject_outliers=False)
        estimates.append([result.K[0, 0], result.K[1, 1], result.K[0, 2], result.K[1, 2], *result.dist[:2]])
        predicted.append([result.std_jacobian[name] for name in ("fx", "fy", "cx", "cy", "k1", "k2")])
        reported.append([result.std[name] for name in ("fx", "fy", "cx", "cy", "k1", "k2")])
    spread = np.std(estimates, axis=0, ddof=1)
    ratio = np.mean(predicted, axis=0) / spread
    assert np.all(np.abs(ratio - 1) <= 0.3), ratio
    # with independent corner errors the reported sigma (the view jackknife of 8 views times Student's factor
    # sqrt(7 / 5) = 1.18 for the jackknife's own noise) is conservative: the jackknife's variance is biased upward
    # (Efron and Stein 1981), here by up to 1.3 in sigma, and the factor adds its 1.18
    assert np.all((np.mean(reported, axis=0) / spread >= 1.0) & (np.mean(reported, axis=0) / spread <= 1.65))


def test_the_view_jackknife_covers_errors_shared_by_a_views_corners(chessboard_9x6):
    """Each view's corners share an error (a board bent or shifted, a blur bias): the Jacobian, which assumes
    independent corners, predicts a fraction of the spread; the view jackknife predicts it."""
    K = np.array([[800.0, 0.0, 330.0], [0.0, 790.0, 235.0], [0.0, 0.0, 1.0]])
    dist = np.array([-0.15, 0.08, 0.0, 0.0, 0.0])
    truth = [project(chessboard_9x6, K, dist, R, t) for R, t in board_poses(chessboard_9x6, 10, 450.0, 30.0)]
    rng = np.random.default_rng(3)
    estimates, jacobian, jackknife = [], [], []
    for _ in range(30):
        views = [points + (points - points.mean(axis=0)) @ rng.normal(0.0, 1.5e-3, (2, 2)) + rng.normal(0.0, 0.3, 2)
                 + rng.normal(0.0, 0.05, points.shape) for points in truth]
        result = calibrate_camera([chessboard_9x6.object_points()] * len(views), views, (640, 480), "radial",
                                  reject_outliers=False)
        estimates.append([result.K[0, 0], result.K[0, 2], result.K[1, 2]])
        jacobian.append([result.std_jacobian[name] for name in ("fx", "cx", "cy")])
        jackknife.append([result.std[name] for name in ("fx", "cx", "cy")])
    spread = np.std(estimates, axis=0, ddof=1)
    assert np.all(np.mean(jacobian, axis=0) / spread < 0.5)
    assert np.all(np.abs(np.mean(jackknife, axis=0) / spread - 1) < 0.35)


def test_a_gross_outlier_view_is_rejected_with_a_reason(chessboard_9x6):
    K = np.array([[800.0, 0.0, 320.0], [0.0, 800.0, 240.0], [0.0, 0.0, 1.0]])
    poses = board_poses(chessboard_9x6, 9, 450.0, 30.0)
    rng = np.random.default_rng(1)
    points = [project(chessboard_9x6, K, np.zeros(5), R, t) + rng.normal(0, 0.1, (54, 2)) for R, t in poses]
    points[4] = points[4] + rng.normal(0, 3.0, points[4].shape)  # a bent board, a wrong detection
    result = calibrate_camera([chessboard_9x6.object_points()] * 9, points, (640, 480))
    assert [index for index, _ in result.rejected] == [4]
    assert "exceeds the outlier limit" in result.rejected[0][1]
    assert list(result.views) == [0, 1, 2, 3, 5, 6, 7, 8]
    assert result.rms < 0.15
    assert abs(result.K[0, 0] - 800) < 1.0


def test_simulated_infrared_hollow_board_calibration_meets_the_targets(chessboard_9x6):
    rng = np.random.default_rng(5)
    poses = board_poses(chessboard_9x6, 10, 370.0, 35.0)
    detections = []
    for R, t in poses:
        image = render_board(chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE, modality="infrared",
                             blur_sigma=1.0, noise_sigma=2.0, supersample=2, rng=rng)
        detections.append(detect_board(image, chessboard_9x6))
    assert all(d is not None for d in detections), "every usable frame must be detected"
    result = calibrate_camera([chessboard_9x6.object_points()] * len(poses), [d.image_points for d in detections],
                              THERMAL_SIZE, distortion="radial")
    focal_error = np.abs(np.diag(result.K)[:2] / np.diag(THERMAL_K)[:2] - 1)
    assert focal_error.max() <= 1e-3
    assert np.abs(result.K[:2, 2] - THERMAL_K[:2, 2]).max() <= 0.5


def test_fewer_than_three_views_are_refused(chessboard_9x6):
    points = [np.zeros((54, 2))] * 2
    with pytest.raises(ValueError, match="at least 3 views"):
        calibrate_camera([chessboard_9x6.object_points()] * 2, points, (640, 480))


def test_mismatched_view_lists_are_refused(chessboard_9x6):
    with pytest.raises(ValueError, match="same views"):
        calibrate_camera([chessboard_9x6.object_points()] * 3, [np.zeros((54, 2))] * 4, (640, 480))


def test_locate_camera_recovers_a_pose_from_non_coplanar_points():
    rng = np.random.default_rng(2)
    K = np.array([[800.0, 0.0, 511.5], [0.0, 800.0, 383.5], [0.0, 0.0, 1.0]])
    R = cv2.Rodrigues(np.array([0.0, np.radians(20.0), 0.0]))[0]
    t = -R @ np.array([400.0, 0.0, 0.0])
    world = np.column_stack([rng.uniform(50, 350, 300), rng.uniform(-100, 100, 300), rng.uniform(430, 570, 300)])
    pixels = project_points(world, K, np.zeros(5), R, t) + rng.normal(0, 0.1, (300, 2))
    R_est, t_est = locate_camera(world, pixels, K, np.zeros(5))
    assert np.abs(R_est - R).max() < 1e-3
    assert np.linalg.norm(t_est - t) < 1.0


def test_locate_camera_needs_six_points():
    with pytest.raises(ValueError, match="at least 6"):
        locate_camera(np.zeros((5, 3)), np.zeros((5, 2)), np.eye(3), np.zeros(5))
