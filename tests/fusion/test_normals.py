import numpy as np
import pytest

from services.fusion.normals import estimate_normals


def test_sphere_normals_are_radial_and_face_the_viewpoint():
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(4000, 3))
    directions[:, 2] = -np.abs(directions[:, 2])  # the half facing -z
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    centre = np.array([0.0, 0.0, 500.0])
    points = centre + 80.0 * directions
    normals = estimate_normals(points, viewpoint=np.zeros(3))
    assert np.median(np.einsum("ni,ni->n", normals, directions)) > 0.999
    assert np.all(np.einsum("ni,ni->n", normals, -points) > 0)


def test_nan_points_get_nan_normals_and_bad_arguments_are_refused():
    points = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1], [np.nan, 0, 0]], dtype=float)
    normals = estimate_normals(points, np.zeros(3), neighbours=4)
    np.testing.assert_allclose(np.abs(normals[:4, 2]), 1.0, atol=1e-9)
    assert np.isnan(normals[4]).all()
    with pytest.raises(ValueError, match="3 neighbours"):
        estimate_normals(points, np.zeros(3), neighbours=2)


def test_only_the_requested_normals_are_estimated_from_all_neighbours():
    x, y = np.meshgrid(np.arange(20.0), np.arange(20.0))
    points = np.column_stack([x.ravel(), y.ravel(), 100 + 0.5 * x.ravel()])
    where = np.zeros(len(points), dtype=bool)
    where[[0, 210]] = True
    normals = estimate_normals(points, np.array([0.0, 0.0, 0.0]), where=where)
    expected = np.array([0.5, 0.0, -1.0]) / np.hypot(0.5, 1.0)
    np.testing.assert_allclose(normals[where], [expected, expected], atol=1e-9)
    assert np.isnan(normals[~where]).all()
