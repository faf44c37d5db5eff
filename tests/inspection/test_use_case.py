"""The inspect use case (services/pipeline/inspect.py) that the command and the scan job call: its outcome and
files, its errors, and the simulated station's part (the billet with its flange) seen from one side."""

import json

import numpy as np
import pytest

from services.errors import InputError
from services.formats.part import load_part
from services.formats.ply import cloud_from_ply
from services.pipeline.inspect import inspect_part, inspection_artifacts, prepare_part_type, report_digest
from services.simulation.hot_part import HotPart, simulated_field, write_forging_part
from services.simulation.thermal import SurfaceTemperature

pytestmark = pytest.mark.integration


def test_the_outcome_and_the_files_a_scan_keeps(station):
    field, _ = station.scan(seed=3)
    outcome = inspect_part(field=field, part=station.prepared)
    files = inspection_artifacts(outcome)
    assert set(files) == {"report.json", "deviation.ply"}
    report = json.loads(files["report.json"])
    assert report["verdict"] == outcome.verdict == "OK" and report["part"] == "billet-90"
    cold = cloud_from_ply(files["deviation.ply"])
    part_points = np.isfinite(outcome.inspection.deviation)
    assert len(cold) == part_points.sum() > 0.99 * len(field["x"])
    np.testing.assert_array_equal(cold["deviation"], outcome.inspection.deviation[part_points])
    assert {"temperature", "temperature_fallback", "red", "green", "blue"} <= set(cold)
    assert len(outcome.deviation["deviation"]) == len(field["x"])  # the field's own points, for the Rerun layer
    digest = report_digest(outcome.report)
    assert digest["verdict"] == "OK" and digest["features"][0]["name"] == "body_diameter"
    json.dumps(digest, allow_nan=False)  # what MQTT and the database get is strict JSON


def test_errors_name_the_field_or_the_part_file(station, tmp_path):
    field, _ = station.scan(seed=4)
    with pytest.raises(InputError, match=r"^scan 7's field: .*temperature"):
        inspect_part(field={k: v for k, v in field.items() if k != "temperature"}, part=station.prepared,
                     source="scan 7's field")
    with pytest.raises(InputError, match=r"^the cold field: .*degC hot"):
        inspect_part(field={**field, "temperature": np.full_like(field["temperature"], 25.0)},
                     part=station.prepared, source="the cold field")
    definition = json.loads(station.part_path.read_text())
    definition["features"][0]["region"] = {"min": [500, 500, 500], "max": [600, 600, 600]}
    bad = tmp_path / "part.json"
    bad.write_text(json.dumps(definition))
    (tmp_path / "billet.stl").write_bytes((station.part_path.parent / "billet.stl").read_bytes())
    with pytest.raises(InputError, match=rf"^{bad}: .*body_diameter"):
        prepare_part_type(load_part(bad))


def test_the_stations_part_is_found_from_one_side(station, tmp_path):
    """The flange pins the billet along its axis; the view's centroid lies off the part's (one side seen,
    the flange's faces dense), which put the start 14 mm off and ICP 24 mm off before the end-to-end
    starts (``align_nominal``)."""
    part = load_part(write_forging_part(tmp_path / "forging"))
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 20.0, 600.0]  # where presets.forging_scene puts it
    hot = HotPart(part.vertices, part.triangles, part.material, SurfaceTemperature(base=1040.0), pose=pose,
                  centre=(0.0, 0.0, 0.0))
    devices = station.rig.devices
    field, _ = simulated_field(hot, devices["camera"], devices["projector"], devices["thermal"],
                               np.random.default_rng(5))
    report = inspect_part(field=field, part=part).report
    alignment = np.array(report["alignment"]["matrix"])
    assert np.abs(alignment[:3, 3] - pose[:3, 3]).max() < 0.5, alignment
    assert report["alignment"]["inlier_fraction"] > 0.99
    diameter = report["features"][0]
    assert abs(diameter["deviation"]) <= diameter["uncertainty"] and report["verdict"] == "OK"
