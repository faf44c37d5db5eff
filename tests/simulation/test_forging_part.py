"""The example part type shipped for the simulated station: what ships is what ``write_forging_part`` makes,
and it is the simulated forging shrunk by its material's thermal strain."""

import json

import numpy as np
import open3d as o3d

from services.formats.part import load_part
from services.inspection.materials import builtin_material
from services.simulation.forging_part import EXAMPLE_DIRECTORY, PART_FILE
from services.simulation.hot_part import write_forging_part
from services.simulation.presets import forging_scene


def test_the_shipped_part_file_and_mesh_are_the_ones_write_forging_part_makes(tmp_path):
    made = write_forging_part(tmp_path)
    assert json.loads(made.read_text()) == json.loads(PART_FILE.read_text())
    shipped = o3d.io.read_triangle_mesh(str(EXAMPLE_DIRECTORY / "forging.stl"))
    fresh = o3d.io.read_triangle_mesh(str(tmp_path / "forging.stl"))
    assert np.allclose(np.asarray(shipped.vertices), np.asarray(fresh.vertices), atol=1e-4)
    assert np.array_equal(np.asarray(shipped.triangles), np.asarray(fresh.triangles))
    assert shipped.remove_duplicated_vertices().is_watertight()  # STL repeats each triangle's corners


def test_the_nominal_is_the_simulated_forging_shrunk_by_its_strain():
    billet = forging_scene().surfaces[0]
    steel = builtin_material("carbon-steel")
    (diameter,) = [feature["nominal"] for feature in json.loads(PART_FILE.read_text())["features"]]
    assert np.isclose(diameter, 2 * billet.radius / (1 + steel.strain(np.array(1040.0))), atol=0.01)
    assert load_part(PART_FILE).name == "forging-station-billet"
