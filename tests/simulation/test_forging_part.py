"""The example part type shipped for the simulated station: what ships is what the module makes, and it is
the simulated forging shrunk by its material's thermal strain."""

import json

import numpy as np
import open3d as o3d

from services.formats.part import load_part
from services.inspection.materials import builtin_material
from services.simulation.forging_part import (EXAMPLE_DIRECTORY, PART_FILE, forging_part_definition, revolved_mesh,
                                              forging_profile, write_forging_part)
from services.simulation.presets import forging_scene


def test_the_shipped_part_file_and_mesh_are_the_ones_the_module_makes(tmp_path):
    made = write_forging_part(tmp_path)
    assert made.read_text() == PART_FILE.read_text()
    shipped = o3d.io.read_triangle_mesh(str(EXAMPLE_DIRECTORY / "forging-cold.stl"))
    fresh = o3d.io.read_triangle_mesh(str(tmp_path / "forging-cold.stl"))
    assert np.allclose(np.asarray(shipped.vertices), np.asarray(fresh.vertices), atol=1e-4)
    assert np.array_equal(np.asarray(shipped.triangles), np.asarray(fresh.triangles))


def test_the_mesh_is_closed_outward_and_encloses_the_profile_s_volume():
    vertices, triangles = revolved_mesh(forging_profile(), segments=720)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    assert mesh.is_watertight() and mesh.is_orientable()
    profile = forging_profile()
    # Pappus: a stack of discs, volume sum(pi r^2 dx) over the profile's horizontal runs.
    expected = sum(np.pi * r0 ** 2 * (x1 - x0) for (x0, r0), (x1, r1) in zip(profile[:-1], profile[1:]) if r0 == r1)
    assert abs(mesh.get_volume() / expected - 1) < 1e-4


def test_the_nominal_is_the_simulated_forging_shrunk_by_its_strain():
    billet, flange = forging_scene().surfaces[:2]
    steel = builtin_material("carbon-steel")
    definition = forging_part_definition()
    diameters = {feature["name"]: feature["nominal"] for feature in definition["features"]}
    assert np.isclose(diameters["billet_diameter"], 2 * billet.radius / (1 + steel.strain(np.array(1040.0))), atol=1e-3)
    assert np.isclose(diameters["flange_diameter"], 2 * flange.radius / (1 + steel.strain(np.array(960.0))), atol=1e-3)
    assert load_part(PART_FILE).name == json.loads(PART_FILE.read_text())["name"] == "simulated-forging"
