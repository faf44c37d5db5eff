"""The part file: a valid file loads with its material and mesh; every kind of bad input is refused by name."""

import json

import numpy as np
import pytest

from services.errors import InputError
from services.formats.part import load_part
from services.simulation.hot_part import write_billet_part


@pytest.fixture(scope="module")
def billet(tmp_path_factory):
    return write_billet_part(tmp_path_factory.mktemp("billet"), segments=60)


def _variant(billet, tmp_path, **changes):
    definition = json.loads(billet.read_text())
    definition.update(changes)
    (tmp_path / "billet.stl").write_bytes((billet.parent / "billet.stl").read_bytes())
    path = tmp_path / "part.json"
    path.write_text(json.dumps(definition))
    return path


def test_valid_part_loads_material_and_mesh(billet):
    part = load_part(billet)
    assert part.name == "billet-90"
    assert part.material.name == "carbon-steel"
    assert part.material.strain(1000.0) == pytest.approx(0.0138)
    assert len(part.triangles) > 100
    extent = np.ptp(part.vertices, axis=0)
    assert extent == pytest.approx([200.0, 90.0, 90.0], abs=0.2)
    assert part.definition.uncertainty.emissivity == 0.85


def test_ovality_is_a_cylinder_measure_of_version_1(billet, tmp_path):
    """Added to version 1: a cylinder may measure its ovality; the files valid before stay valid."""
    definition = json.loads(billet.read_text())
    body = definition["features"][0]
    ovality = {**body, "name": "body_ovality", "measure": "ovality", "nominal": 0.0, "tolerance": [0.0, 0.3]}
    path = _variant(billet, tmp_path, features=[body, ovality])
    features = load_part(path).definition.features
    assert [(feature.name, feature.measure) for feature in features] == [("body_diameter", "diameter"),
                                                                         ("body_ovality", "ovality")]
    assert load_part(billet).definition.version == 1


def test_custom_material_table(billet, tmp_path):
    path = _variant(billet, tmp_path, material={"name": "c45", "elongation": [[0, -2e-4], [20, 0], [1100, 0.015]]})
    material = load_part(path).material
    assert material.name == "c45"
    assert material.strain(20.0) == 0
    assert material.strain(560.0) == pytest.approx(0.0075)


@pytest.mark.parametrize("changes, message", [
    ({"material": "unobtainium"}, "material: unknown material 'unobtainium'"),
    ({"material": {"elongation": [[20, 0], [900, 0.01], [800, 0.012]]}}, "must increase strictly"),
    ({"material": {"elongation": [[100, 0], [900, 0.01]]}}, "must cover the reference temperature"),
    ({"version": 2}, "version"),
    ({"nominal": "billet.step"}, "must be one of .stl, .ply, .obj"),
    ({"surface_tolerance": [0.5, -0.5]}, "surface_tolerance"),
    ({"features": [{"name": "d", "type": "cylinder", "measure": "diameter", "region": {"min": [0, 0, 0],
                                                                                     "max": [1, 1, 1]}}]},
     "needs 'nominal' and 'tolerance'"),
    ({"features": [{"name": "d", "type": "sphere", "measure": "flatness", "region": {"min": [0, 0, 0],
                                                                                   "max": [1, 1, 1]},
                    "nominal": 1, "tolerance": [-1, 1]}]}, "measures one of"),
    ({"features": [{"name": "d", "type": "plane", "measure": "ovality", "region": {"min": [0, 0, 0],
                                                                                  "max": [1, 1, 1]},
                    "nominal": 0, "tolerance": [0, 0.3]}]}, "a plane measures one of \\['flatness'\\]"),
    ({"features": [{"name": "l", "type": "distance", "between": ["a", "b"], "nominal": 1, "tolerance": [-1, 1]}]},
     "refers to 'a'"),
    ({"features": [{"name": "p", "type": "plane", "region": {"min": [1, 0, 0], "max": [0, 1, 1]}}]},
     "min must lie below max"),
    ({"colour": "red"}, "Extra inputs are not permitted"),
])
def test_bad_part_files_are_refused_naming_the_file(billet, tmp_path, changes, message):
    path = _variant(billet, tmp_path, **changes)
    with pytest.raises(InputError, match=message) as error:
        load_part(path)
    assert str(path) in str(error.value)


def test_mesh_that_does_not_load(billet, tmp_path):
    path = _variant(billet, tmp_path)
    (tmp_path / "billet.stl").write_text("solid nothing\nendsolid nothing\n")
    with pytest.raises(InputError, match="not a readable triangle mesh"):
        load_part(path)
    (tmp_path / "billet.stl").unlink()
    with pytest.raises(InputError, match="is missing"):
        load_part(path)


def test_unreadable_part_file(tmp_path):
    with pytest.raises(InputError, match="cannot read the part file"):
        load_part(tmp_path / "absent.json")
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(InputError, match="broken.json"):
        load_part(tmp_path / "broken.json")
