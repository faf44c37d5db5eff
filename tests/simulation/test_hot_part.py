"""The hot part: a closed outward mesh, thermal expansion of known size, bumps of known height, the scan."""

import numpy as np
import pytest

from services.inspection.materials import builtin_material
from services.simulation.hot_part import (Bump, HotPart, ScanNoise, billet_pose, cylinder_mesh, simulated_field,
                                          vertex_normals)
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature, ThermalEffects

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


def test_tube_mesh_is_closed_outward_and_open_through_its_bore():
    from services.open3d_loader import open3d
    from services.simulation.hot_part import tube_mesh

    vertices, triangles = tube_mesh(45.0, 35.0, 200.0, 90)
    corners = vertices[triangles]
    volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() / 6
    assert volume == pytest.approx(np.pi * (45.0**2 - 35.0**2) * 200.0, rel=0.01)  # the wall, not the bore
    o3d = open3d()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    assert mesh.is_watertight()
    # the inner wall's normals point to the axis
    centre = corners.mean(axis=1)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    inner = (np.hypot(centre[:, 1], centre[:, 2]) < 36.0) & (np.abs(centre[:, 0]) < 99.0)
    assert np.all(np.einsum("ij,ij->i", normal[inner, 1:], centre[inner, 1:]) < 0)
    with pytest.raises(ValueError, match="inner radius"):
        tube_mesh(30.0, 35.0, 100.0)


def test_the_thermal_frame_mixes_the_part_with_the_backdrop_along_its_silhouette():
    from services.simulation.hot_part import Backdrop, simulated_thermal_frame

    thermal = forging_rig(0.35).devices["thermal"]
    vertices, triangles = cylinder_mesh(45.0, 200.0, 90)
    part = HotPart(vertices, triangles, STEEL, SurfaceTemperature(base=1000.0), pose=billet_pose())
    wall = Backdrop(centre=(0.0, 20.0, 760.0), temperature_c=60.0)
    image = simulated_thermal_frame(part, thermal, np.random.default_rng(0), backdrop=wall)
    assert np.sum(np.abs(image - 1000.0) < 1.0) > 1000  # the part's interior reads its temperature
    assert np.sum(np.abs(image - 60.0) < 1.0) > 10000  # the wall its own
    mixed = (image > 100.0) & (image < 950.0)
    assert mixed.sum() > 100  # the silhouette's pixels read neither
    sharp = simulated_thermal_frame(part, thermal, np.random.default_rng(0), backdrop=wall,
                                    effects=ThermalEffects(supersample=1, blur_sigma=0.0, netd=0.0))
    assert np.sum((sharp > 100.0) & (sharp < 950.0)) == 0  # one ray per pixel, no blur: no mix
