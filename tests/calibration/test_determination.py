import cv2
import numpy as np
import pytest

from services.calibration.camera import _calibrate_views, calibrate_camera, student_predictive_factor, view_jackknife
from services.calibration.determination import _tilt_advice, poorly_determined
from services.formats.board import parse_board

BOARD = parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0}')
K = np.array([[400.0, 0.0, 161.3], [0.0, 400.0, 127.6], [0.0, 0.0, 1.0]])
DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])
SIZE = (320, 256)


def views(count: int, tilt_deg: float, axes=None, seed: int = 1, undistorted: bool = False) -> list[np.ndarray]:
    """Projected corners (0.05 px noise) of ``count`` poses tilted by ``tilt_deg`` about turning axes (or ``axes``)."""
    rng = np.random.default_rng(seed)
    centre = BOARD.object_points().mean(axis=0)
    points = []
    for index in range(count):
        angle = 2 * np.pi * index / count
        axis = np.array([np.cos(angle), np.sin(angle)]) if axes is None else axes[index % len(axes)] * (-1) ** index
        R = cv2.Rodrigues(np.radians(tilt_deg) * np.array([axis[0], axis[1], 0.0]))[0]
        t = np.array([rng.uniform(-15, 15), rng.uniform(-15, 15), rng.uniform(380, 480)]) - R @ centre
        projected = cv2.projectPoints(BOARD.object_points(), cv2.Rodrigues(R)[0], t, K,
                                      np.zeros(5) if undistorted else DIST)[0].reshape(-1, 2)
        assert projected.min() > 0 and np.all(projected.max(axis=0) < SIZE)
        points.append(projected + rng.normal(0.0, 0.05, projected.shape))
    return points


def calibrate(points):
    return calibrate_camera([BOARD.object_points()] * len(points), points, SIZE, "radial")


def test_a_good_view_set_is_not_called_poorly_determined():
    assert poorly_determined(calibrate(views(12, 35.0))) == []


def test_nearly_flat_views_leave_the_focal_length_poorly_determined():
    messages = poorly_determined(calibrate(views(6, 3.0)))
    assert len(messages) == 1 and messages[0].startswith("focal length poorly determined")


@pytest.mark.parametrize(("axis", "weak", "advice"), [((1.0, 0.0), "y", "tilted about the vertical axis"),
                                                      ((0.0, 1.0), "x", "tilted about the horizontal axis")])
def test_views_tilted_about_one_axis_leave_the_principal_point_poorly_determined(axis, weak, advice):
    """Without lens distortion to anchor it, the principal point along one axis needs tilts about the other."""
    points = views(6, 30.0, axes=[np.array(axis)], undistorted=True)
    result = calibrate_camera([BOARD.object_points()] * len(points), points, SIZE, "none")
    principal = [m for m in poorly_determined(result) if m.startswith("principal point poorly determined")]
    assert len(principal) == 1 and advice in principal[0]
    assert result.std[f"c{weak}"] > 3 * result.std["cx" if weak == "y" else "cy"]
    assert advice in _tilt_advice(result.rotations)


def test_the_jackknife_correlation_is_a_correlation_matrix():
    result = calibrate(views(12, 35.0))
    assert result.correlation.shape == (len(result.std), len(result.std))
    assert np.allclose(np.diag(result.correlation), 1.0)
    assert np.all(np.abs(result.correlation) <= 1.0 + 1e-9)
    # the reported sigma is the jackknife's (the square root of the covariance's diagonal) times Student's factor
    points = views(12, 35.0)
    jackknife = np.sqrt(np.diag(view_jackknife([BOARD.object_points()] * len(points), points, SIZE, "radial",
                                               _calibrate_views([BOARD.object_points().astype(np.float32)] * len(points),
                                                                [p.astype(np.float32) for p in points], SIZE,
                                                                "radial"))))
    reported = np.array([result.std[name] for name in ("fx", "fy", "cx", "cy", "k1", "k2")])
    assert np.allclose(reported, student_predictive_factor(12) * jackknife, rtol=1e-3)
