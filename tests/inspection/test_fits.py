"""Robust plane, cylinder and sphere fits recover known shapes from partial, noisy views with outliers."""

import numpy as np
import pytest

from services.inspection.cylinder import fit_cylinder
from services.inspection.distance import feature_distance
from services.inspection.plane import fit_plane
from services.inspection.sphere import fit_sphere

pytestmark = pytest.mark.integration

rng = np.random.default_rng(3)


def _with_outliers(points, fraction=0.03, size=2.0):
    points = points.copy()
    chosen = rng.choice(len(points), int(fraction * len(points)), replace=False)
    points[chosen] += rng.normal(0, size, (len(chosen), 3))
    return points


def test_cylinder_from_a_half_view():
    angle = rng.uniform(-np.pi / 2, np.pi / 2, 20000)  # one side only
    x = rng.uniform(-80, 80, 20000)
    radius = 45.62 + rng.normal(0, 0.02, 20000)
    axis = np.array([0.96, 0.2, 0.19])
    axis /= np.linalg.norm(axis)
    u = np.cross(axis, [0, 0, 1.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    centre = np.array([5.0, 20.0, 600.0])
    points = centre + np.outer(x, axis) + radius[:, None] * (np.outer(np.cos(angle), u) + np.outer(np.sin(angle), v))
    fit = fit_cylinder(_with_outliers(points), centre + [1.0, -2.0, 1.5], [1.0, 0.1, 0.2], 45.0)
    assert fit.radius == pytest.approx(45.62, abs=0.003)
    assert abs(fit.axis @ axis) == pytest.approx(1.0, abs=1e-6)
    assert fit.noise == pytest.approx(0.02, rel=0.2)
    assert 0 < fit.radius_std < 0.002


def test_sphere_cap_and_plane():
    direction = rng.normal(size=(20000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    direction = direction[direction[:, 2] < -0.3]  # a cap facing the camera
    points = np.array([10.0, -5.0, 500.0]) + (30.0 + rng.normal(0, 0.02, len(direction)))[:, None] * direction
    sphere = fit_sphere(_with_outliers(points))
    assert sphere.radius == pytest.approx(30.0, abs=0.005)
    assert sphere.center == pytest.approx([10.0, -5.0, 500.0], abs=0.01)

    flat = np.column_stack([rng.uniform(-50, 50, 5000), rng.uniform(-50, 50, 5000), rng.normal(0, 0.02, 5000)])
    plane = fit_plane(_with_outliers(flat))
    assert abs(plane.normal[2]) == pytest.approx(1.0, abs=1e-5)
    assert plane.point[2] == pytest.approx(0.0, abs=0.002)
    assert 0.1 < plane.flatness < 0.2  # the noise's range over the kept points


def test_distances_between_features():
    square = np.column_stack([rng.uniform(-20, 20, 2000), rng.uniform(-20, 20, 2000)])
    face_a = fit_plane(np.column_stack([square, np.zeros(2000)]))
    face_b = fit_plane(np.column_stack([square + 3, np.full(2000, 200.0)]))
    assert feature_distance(face_a, face_b) == pytest.approx(200.0, abs=1e-9)
    direction = rng.normal(size=(3000, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    ball = fit_sphere(np.array([0.0, 0.0, 50.0]) + 10 * direction)
    assert feature_distance(face_a, ball) == pytest.approx(50.0, abs=1e-6)
    other = fit_sphere(np.array([30.0, 40.0, 50.0]) + 10 * direction)
    assert feature_distance(ball, other) == pytest.approx(50.0, abs=1e-6)


def test_too_few_points():
    with pytest.raises(ValueError, match="at least 5 points"):
        fit_cylinder(np.zeros((3, 3)), np.zeros(3), [1, 0, 0], 1.0)
    with pytest.raises(ValueError, match="at least 4 points"):
        fit_sphere(np.zeros((3, 3)))
