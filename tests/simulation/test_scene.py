import json
import re

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from services.errors import InputError
from services.simulation.scene import Albedo, Mesh, load_scene, parse_scene, surface_albedo

PLANE = {"type": "plane", "center": [0, 0, 500], "normal": [0, 0, -1], "u_axis": [1, 0, 0], "size": [300, 200]}


def _write_ply_mesh(path, vertices, faces):
    vertex = np.array([tuple(v) for v in vertices], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    face = np.array([(list(f),) for f in faces], dtype=[("vertex_indices", "i4", (3,))])
    PlyData([PlyElement.describe(vertex, "vertex"), PlyElement.describe(face, "face")]).write(str(path))


def test_scene_file_with_every_surface_type_loads(tmp_path):
    _write_ply_mesh(tmp_path / "part.ply", [[0, 0, 400], [10, 0, 400], [0, 10, 400]], [[0, 1, 2]])
    surfaces = [PLANE, {"type": "sphere", "center": [0, 0, 480], "radius": 100, "albedo": {"base": 0.3}},
                {"type": "cylinder", "center": [0, 0, 600], "axis": [1, 0, 0], "radius": 60, "length": 200,
                 "capped": False},
                {"type": "mesh", "vertices": [[0, 0, 1], [1, 0, 1], [0, 1, 1]], "faces": [[0, 1, 2]]},
                {"type": "mesh", "ply": "part.ply"}]
    (tmp_path / "scene.json").write_text(json.dumps({"ambient": 0.1, "surfaces": surfaces}))
    scene = load_scene(tmp_path / "scene.json")
    assert [s.type for s in scene.surfaces] == ["plane", "sphere", "cylinder", "mesh", "mesh"]
    assert scene.ambient == 0.1 and scene.surfaces[1].albedo.base == 0.3 and not scene.surfaces[2].capped
    np.testing.assert_allclose(scene.surfaces[4].triangles(), [[[0, 0, 400], [10, 0, 400], [0, 10, 400]]])


@pytest.mark.parametrize("surface, field", [
    ({**PLANE, "colour": 3}, "surfaces[0].colour"),
    ({**PLANE, "u_axis": [0, 0, 1]}, "surfaces[0]"),
    ({**PLANE, "size": [300, -1]}, "surfaces[0].size[1]"),
    ({"type": "sphere", "center": [0, 0, 1], "radius": 0}, "surfaces[0].radius"),
    ({"type": "cylinder", "center": [0, 0, 1], "axis": [0, 0, 0], "radius": 1, "length": 1},
     "surfaces[0].axis"),
    ({"type": "mesh", "vertices": [[0, 0, 1]], "faces": [[0, 1, 2]]}, "surfaces[0]"),
    ({"type": "mesh", "ply": "x.ply", "vertices": [[0, 0, 1]], "faces": [[0, 0, 0]]}, "surfaces[0]"),
    ({"type": "torus"}, "surfaces[0]"),
    ({**PLANE, "albedo": {"base": 1.5}}, "surfaces[0].albedo.base"),
])
def test_invalid_surfaces_are_refused_naming_the_field(surface, field):
    with pytest.raises(InputError, match=re.escape(f"my.json: {field}")):
        parse_scene(json.dumps({"surfaces": [surface]}), "my.json")


def test_missing_or_malformed_mesh_file_is_named(tmp_path):
    text = json.dumps({"surfaces": [{"type": "mesh", "ply": "gone.ply"}]})
    with pytest.raises(InputError, match=r"surfaces.0.ply: mesh file .*gone.ply is missing"):
        parse_scene(text, "s.json", tmp_path)
    (tmp_path / "gone.ply").write_text("not a ply")
    with pytest.raises(InputError, match="not a PLY triangle mesh"):
        parse_scene(text, "s.json", tmp_path)


def test_missing_scene_file_is_named(tmp_path):
    with pytest.raises(InputError, match="nothing.json: cannot read"):
        load_scene(tmp_path / "nothing.json")


def test_texture_is_smooth_bounded_and_deterministic_by_seed():
    albedo = Albedo(base=0.5, texture_amplitude=0.3, feature_size=20.0, seed=7)
    x = np.linspace(0, 200, 2001)
    points = np.column_stack([x, np.zeros_like(x), np.full_like(x, 500)])
    values = albedo.evaluate(points)
    assert np.all((values >= 0.2 - 1e-6) & (values <= 0.8 + 1e-6))
    assert values.std() > 0.03
    assert np.abs(np.diff(values)).max() < 0.3 * 2 * np.pi / 20 * 0.1 * 1.01  # |slope| <= amplitude * 2 pi / size
    np.testing.assert_array_equal(values, Albedo(base=0.5, texture_amplitude=0.3, feature_size=20.0,
                                                 seed=7).evaluate(points))
    assert not np.allclose(values, Albedo(base=0.5, texture_amplitude=0.3, feature_size=20.0, seed=8).evaluate(points))
    np.testing.assert_array_equal(Albedo(base=0.4).evaluate(points), 0.4)


def test_surface_albedo_follows_the_surface_index():
    scene = parse_scene(json.dumps({"surfaces": [{**PLANE, "albedo": {"base": 0.2}},
                                                 {"type": "sphere", "center": [0, 0, 1], "radius": 1,
                                                  "albedo": {"base": 0.9}}]}))
    values = surface_albedo(scene, np.zeros((3, 3)), np.array([1, -1, 0]))
    np.testing.assert_array_equal(values, [0.9, np.nan, 0.2])


def test_unloaded_ply_mesh_cannot_be_traced():
    with pytest.raises(ValueError, match="load_scene"):
        Mesh(ply="part.ply").triangles()
