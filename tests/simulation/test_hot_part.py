"""The hot part: a closed outward mesh, thermal expansion of known size, bumps of known height, the scan."""

import numpy as np
import pytest

from services.inspection.materials import builtin_material
from services.simulation.hot_part import (Bump, HotPart, ScanNoise, billet_pose, cylinder_mesh, simulated_field,
                                          vertex_normals)
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature

STEEL = builtin_material("carbon-steel")


def test_cylinder_mesh_is_closed_and_outward():
    vertices, triangles = cylinder_mesh(45.0, 200.0, 90)
    corners = vertices[triangles]
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6
    polygon_area = 0.5 * 90 * 45.0**2 * np.sin(2 * np.pi / 90)
    assert volume == pytest.approx(polygon_area * 200.0, rel=1e-9)
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # every edge shared by two triangles: watertight


def test_uniform_expansion_and_bumps():
    vertices, triangles = cylinder_mesh(45.0, 200.0, 180)
    hot = HotPart(vertices, triangles, STEEL, SurfaceTemperature(base=1000.0)).hot_vertices_part()
    assert 2 * np.hypot(hot[:, 1], hot[:, 2]).max() == pytest.approx(91.242, abs=1e-9)
    assert np.ptp(hot[:, 0]) == pytest.approx(200 * 1.0138, abs=1e-9)
    dented = HotPart(vertices, triangles, STEEL, SurfaceTemperature(base=20.0),
                     bumps=(Bump((0.0, 0.0, 45.0), 4.0, -0.3),))
    moved = np.linalg.norm(dented.cold_vertices() - vertices, axis=1)
    assert moved.max() == pytest.approx(0.3, abs=0.01)
    normals = vertex_normals(vertices, triangles)
    assert normals[np.argmax(moved)] @ [0, 0, 1] > 0.99


def test_simulated_field_sees_the_hot_part():
    rig = forging_rig(0.3)
    vertices, triangles = cylinder_mesh(45.0, 200.0, 120)
    part = HotPart(vertices, triangles, STEEL, SurfaceTemperature(base=1000.0, gradient=[0.2, 0.0, 0.0]),
                   pose=billet_pose())
    devices = rig.devices
    field, truth = simulated_field(part, devices["camera"], devices["projector"], devices["thermal"],
                                   np.random.default_rng(0), ScanNoise(structured_light_mm=0.0, netd_k=0.0))
    assert len(field["x"]) > 1000
    measured = np.column_stack([field["x"], field["y"], field["z"]])
    assert np.abs(measured - truth).max() < 1e-3  # no noise: the true hot surface
    seen = np.isfinite(field["temperature"])
    assert 0.5 < seen.mean() <= 1.0
    local = (truth - billet_pose()[:3, 3]) @ billet_pose()[:3, :3]
    expected = 1000.0 + 0.2 * local[:, 0] / 1.0138  # the field is given in cold coordinates
    assert field["temperature"][seen] == pytest.approx(expected[seen], abs=0.05)
