"""The nominal's tabulated signed distance against exact mesh queries."""

import numpy as np
import pytest

from services.inspection.distance_grid import sample_distance_grid
from services.inspection.nominal import GRID_BAND_MM, NominalSurface
from services.open3d_loader import open3d
from services.simulation.hot_part import cylinder_mesh

pytestmark = pytest.mark.integration


def _box():
    box = open3d().geometry.TriangleMesh.create_box(60.0, 30.0, 20.0)
    return np.asarray(box.vertices) - [30.0, 15.0, 10.0], np.asarray(box.triangles)


@pytest.mark.parametrize("mesh", [lambda: cylinder_mesh(45.0, 200.0, 360), _box], ids=["billet", "box"])
def test_grid_matches_exact_distances_within_its_tolerance(mesh):
    vertices, triangles = mesh()
    nominal = NominalSurface(vertices, triangles)
    rng = np.random.default_rng(1)
    on_surface = nominal.samples[rng.integers(0, len(nominal.samples), 40000)]
    points = on_surface + rng.uniform(-GRID_BAND_MM, GRID_BAND_MM, (40000, 1)) * nominal.sample_normals[
        rng.integers(0, len(nominal.samples), 40000)] + rng.normal(0, 0.3, (40000, 3))
    exact = nominal.closest(points).signed_distance
    fast = nominal.signed_distance(points)
    assert np.all(np.isfinite(fast))
    assert np.max(np.abs(fast - exact)) < 0.01
    interpolated, needs_exact = sample_distance_grid(nominal.grid, points)
    trusted = np.isfinite(interpolated) & ~needs_exact
    assert trusted.mean() > 0.5  # the grid, not the mesh, answers most of them
    assert np.max(np.abs(interpolated[trusted] - exact[trusted])) < 0.01
    # the ICP's planes: the distance and its gradient, the outward normal of the closest point
    distance, gradient = nominal.signed_distance_gradient(points)
    assert np.max(np.abs(distance - exact)) < 0.01
    closest = nominal.closest(points)
    off = np.abs(exact) > 0.05
    normal = (points[off] - closest.points[off]) / exact[off, None]
    cosine = np.einsum("ij,ij->i", gradient[off], normal) / np.linalg.norm(gradient[off], axis=1)
    assert np.degrees(np.arccos(np.clip(cosine.min(), -1, 1))) < 5
    assert np.abs(np.linalg.norm(gradient, axis=1) - 1).max() < 0.05


def test_edges_are_queried_exactly_and_far_points_too():
    vertices, triangles = _box()
    nominal = NominalSurface(vertices, triangles)
    edge = np.array([[30.2, 15.2, 0.0], [-30.3, 0.0, 10.3]])  # just outside an edge of the box
    far = np.array([[0.0, 0.0, 40.0]])
    _, needs_exact = sample_distance_grid(nominal.grid, edge)
    assert needs_exact.all()
    interpolated, _ = sample_distance_grid(nominal.grid, far)
    assert np.isnan(interpolated).all()
    assert nominal.signed_distance(far)[0] == pytest.approx(30.0, abs=1e-4)
    assert nominal.signed_distance(edge) == pytest.approx(nominal.closest(edge).signed_distance, abs=1e-9)
