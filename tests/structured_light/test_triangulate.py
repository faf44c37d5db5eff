import cv2
import numpy as np
import pytest

from services.geometry.camera import normalized_coordinates, project_points
from services.structured_light.triangulate import camera_ray_table, triangulate


def _rotation(rx, ry, rz):
    return cv2.Rodrigues(np.deg2rad([rx, ry, rz]))[0]


def _rig(projector_dist):
    camera_R = _rotation(1.0, 20.0, 0.5)  # toed in toward the projector
    camera_C = np.array([400.0, 10.0, -5.0])
    camera = dict(K=np.array([[1400.0, 0, 640], [0, 1395.0, 400], [0, 0, 1]]),
                  dist=np.array([-0.12, 0.08, 0.001, -0.0007, -0.02]), R=camera_R, t=-camera_R @ camera_C)
    projector = dict(K=np.array([[1300.0, 0, 515], [0, 1310.0, 760], [0, 0, 1]]), dist=projector_dist,
                     R=_rotation(0.3, 0.2, -0.1), t=np.array([1.0, -2.0, 3.0]))
    return camera, projector


def _points(rng, camera, n=2000):
    """Random points inside the camera's 1280x800 view, where its distortion model is invertible."""
    points = np.column_stack([rng.uniform(-150, 150, n), rng.uniform(-100, 100, n), rng.uniform(430, 570, n)])
    pixels = project_points(points, **camera)
    inside = (pixels[:, 0] >= 0) & (pixels[:, 0] < 1280) & (pixels[:, 1] >= 0) & (pixels[:, 1] < 800)
    assert inside.mean() > 0.5
    return points[inside]


@pytest.mark.parametrize("projector_dist", [
    np.zeros(0),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02]),
    np.array([0.05, -0.1, 0.0015, 0.001, 0.02, 0.01, -0.02, 0.005, 0.001, -0.0005, 0.0008, 0.0002, 0.01, -0.008]),
], ids=["pinhole", "five", "fourteen"])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_recovers_points_through_both_distortions(projector_dist, axis):
    rng = np.random.default_rng(1)
    camera, projector = _rig(projector_dist)
    points = _points(rng, camera)
    camera_pixels = project_points(points, **camera)
    projector_pixels = project_points(points, **projector)
    rays = normalized_coordinates(camera_pixels, camera["K"], camera["dist"])
    coordinate = projector_pixels[:, 0 if axis == "x" else 1]
    result = triangulate(rays, coordinate, axis, camera["R"], camera["t"], projector["K"], projector["dist"],
                         projector["R"], projector["t"])
    assert result.dtype == np.float32
    assert np.abs(result - points).max() < 2e-4  # float32 output at 500 mm


def test_projector_distortion_matters():
    """Ignoring a real projector distortion would move points by far more than the accuracy target."""
    rng = np.random.default_rng(2)
    camera, projector = _rig(np.array([0.05, -0.1, 0.0015, 0.001, 0.02]))
    points = _points(rng, camera)
    rays = normalized_coordinates(project_points(points, **camera), camera["K"], camera["dist"])
    coordinate = project_points(points, **projector)[:, 0]
    ignoring = triangulate(rays, coordinate, "x", camera["R"], camera["t"], projector["K"], np.zeros(5),
                           projector["R"], projector["t"])
    assert np.abs(ignoring - points).max() > 1.0


def test_ray_table_matches_pointwise_undistortion():
    camera, _ = _rig(np.zeros(0))
    table = camera_ray_table(camera["K"], camera["dist"], 64, 48)
    assert table.shape == (48, 64, 2)
    expected = normalized_coordinates(np.array([[10.0, 20.0], [63.0, 47.0]]), camera["K"], camera["dist"])
    np.testing.assert_allclose(table[[20, 47], [10, 63]], expected, atol=1e-7)


def test_unreachable_line_gives_nan():
    camera, projector = _rig(np.zeros(0))
    rays = np.array([[0.0, 0.0]])
    # a column far outside any plausible projector field cannot be met in front of both devices
    result = triangulate(rays, np.array([-1e7]), "x", camera["R"], camera["t"], projector["K"],
                         projector["dist"], projector["R"], projector["t"])
    assert np.isnan(result).all()


def test_rejects_bad_shapes():
    camera, projector = _rig(np.zeros(0))
    with pytest.raises(ValueError, match="camera rays but"):
        triangulate(np.zeros((3, 2)), np.zeros(2), "x", camera["R"], camera["t"], projector["K"],
                    projector["dist"], projector["R"], projector["t"])
    with pytest.raises(ValueError, match="coded axis"):
        triangulate(np.zeros((3, 2)), np.zeros(3), "z", camera["R"], camera["t"], projector["K"],
                    projector["dist"], projector["R"], projector["t"])
