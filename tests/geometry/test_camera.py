import cv2
import numpy as np
import pytest

from services.geometry.camera import camera_center, normalized_coordinates, pixel_grid, pixel_rays, project_points

K = np.array([[1200.0, 0, 630], [0, 1190.0, 410], [0, 0, 1]])
DIST = np.array([-0.15, 0.1, 0.001, -0.002, -0.03])
R = cv2.Rodrigues(np.array([0.05, -0.3, 0.02]))[0]
C = np.array([300.0, -20.0, 10.0])
T = -R @ C


def test_pose_convention_world_to_device():
    np.testing.assert_allclose(camera_center(R, T), C)
    # the centre's own pixel is undefined; a point on the optical axis lands on the principal point
    on_axis = C + 500 * R[2]
    np.testing.assert_allclose(project_points(on_axis[None], K, DIST, R, T)[0], K[:2, 2], atol=1e-9)


def test_rays_through_pixels_hit_the_projected_points():
    rng = np.random.default_rng(0)
    pixels = rng.uniform([0, 0], [1280, 800], size=(500, 2))
    origin, directions = pixel_rays(pixels, K, DIST, R, T)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1)
    points = origin + rng.uniform(300, 900, size=(500, 1)) * directions
    np.testing.assert_allclose(project_points(points, K, DIST, R, T), pixels, atol=1e-8)


def test_points_behind_the_device_are_nan():
    behind = C - 100 * R[2]
    assert np.isnan(project_points(behind[None], K, DIST, R, T)).all()


def test_grid_and_checks():
    grid = pixel_grid(3, 2)
    np.testing.assert_array_equal(grid, [[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]])
    with pytest.raises(ValueError, match="shape"):
        normalized_coordinates(np.zeros((4, 3)), K, DIST)
    with pytest.raises(ValueError, match="coefficients"):
        project_points(np.zeros((1, 3)), K, np.zeros(3), R, T)
