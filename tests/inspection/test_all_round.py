"""Inspection all round: a shaft seen by four heads (a merged field with a ``head`` property), its diameter from
the whole circumference, its ovality, the length between end faces seen by different heads, a dent on the side
away from the first head, and what one head alone cannot decide."""

import json

import numpy as np
import pytest

from services.cli.main import main
from services.formats.part import load_part
from services.formats.ply import read_cloud, write_cloud
from services.inspection.inspect import head_points, inspect_field, prepare_part
from services.simulation.hot_part import Bump, all_round_field, hot_shaft, station_heads, write_shaft_part

pytestmark = pytest.mark.integration

SEGMENTS = 180
DENSITY = 2.0  # points per mm^2: about 200 000 points on the shaft
STRAIN_1000 = 0.0138  # carbon steel at 1000 degC (EN 1993-1-2)
# the dent faces away from head 0: on the azimuth of head 2 (225 degrees), 40 mm toward +x
DENT = (40.0, 45.0 * np.cos(np.radians(225.0)), 45.0 * np.sin(np.radians(225.0)))


@pytest.fixture(scope="module")
def shaft(tmp_path_factory):
    path = write_shaft_part(tmp_path_factory.mktemp("shaft"), segments=SEGMENTS)
    return path, prepare_part(load_part(path))


def _scan(seed, **shaft):
    return all_round_field(hot_shaft(segments=SEGMENTS, **shaft), np.random.default_rng(seed), points_per_mm2=DENSITY)


def _feature(report, name):
    return next(feature for feature in report["features"] if feature["name"] == name)


def test_round_shaft_measured_all_round(shaft):
    field, truth = _scan(0)
    # the end faces come from different heads: +x from heads 0 and 2, -x from heads 1 and 3
    on_face = np.hypot(truth[:, 1], truth[:, 2]) < 40.0
    assert set(np.unique(field["head"][on_face & (truth[:, 0] > 0)])) == {0, 2}
    assert set(np.unique(field["head"][on_face & (truth[:, 0] < 0)])) == {1, 3}
    inspection = inspect_field(field=field, part=shaft[1])
    report = inspection.report
    diameter = _feature(report, "body_diameter")
    assert diameter["hot"] == pytest.approx(90.0 * (1 + STRAIN_1000), abs=0.03)
    assert diameter["cold"] == pytest.approx(90.0, abs=0.03)
    assert abs(diameter["deviation"]) <= diameter["uncertainty"] and diameter["verdict"] == "OK"
    ovality = _feature(report, "body_ovality")
    assert 0 <= ovality["cold"] < 0.02
    assert ovality["verdict"] == "OK"  # a form measure near 0 is OK, not NotDecidable at its lower limit
    length = _feature(report, "length")
    assert length["hot"] == pytest.approx(300.0 * (1 + STRAIN_1000), abs=0.1)
    assert length["cold"] == pytest.approx(300.0, abs=0.1) and length["verdict"] == "OK"
    assert report["surface"]["defects"] == [] and report["verdict"] == "OK"
    counts = {entry["head"]: entry for entry in report["heads"]}
    assert sorted(counts) == [0, 1, 2, 3]
    assert sum(entry["points"] for entry in counts.values()) == len(field["x"])
    for head, entry in counts.items():
        assert entry["points"] == np.count_nonzero(field["head"] == head) > 40000
        assert entry["part_points"] == entry["points"]  # nothing but the part in this field
    assert inspection.heads[0].head == 0 and inspection.heads[0].points == counts[0]["points"]


def test_dent_on_the_side_away_from_the_first_head(shaft):
    field, truth = _scan(1, bumps=(Bump(DENT, 4.0, -0.3),))
    near = np.linalg.norm(truth - np.asarray(DENT), axis=1) < 4.0
    assert near.sum() > 50 and set(np.unique(field["head"][near])) == {2}  # head 0 never saw it
    report = inspect_field(field=field, part=shaft[1]).report
    defects = report["surface"]["defects"]
    assert len(defects) == 1
    assert defects[0]["depth"] == pytest.approx(-0.3, abs=0.05)
    centre = np.asarray(defects[0]["center"])
    # the shaft is symmetric about its axis and end to end: compare what the symmetry leaves
    assert abs(abs(centre[0]) - 40.0) < 3.0 and np.hypot(centre[1], centre[2]) == pytest.approx(45.0, abs=1.0)
    assert report["surface"]["verdict"] == "OK" and report["verdict"] == "OK"


def test_oval_and_long_shaft(shaft):
    field, _ = _scan(2, ovality=0.5, length=302.0)
    report = inspect_field(field=field, part=shaft[1]).report
    ovality = _feature(report, "body_ovality")
    assert ovality["cold"] == pytest.approx(0.5, abs=0.03)
    assert ovality["hot"] == pytest.approx(0.5 * (1 + STRAIN_1000), abs=0.03)
    assert ovality["verdict"] == "NotOK"
    length = _feature(report, "length")
    assert length["cold"] == pytest.approx(302.0, abs=0.1) and length["verdict"] == "NotOK"
    diameter = _feature(report, "body_diameter")
    assert diameter["cold"] == pytest.approx(90.0, abs=0.03) and diameter["verdict"] == "OK"
    assert report["verdict"] == "NotOK"


def test_one_head_cannot_decide_ovality_or_length(shaft):
    field, _ = _scan(3, ovality=0.5)
    first = field["head"] == 0
    report = inspect_field(field={name: values[first] for name, values in field.items()}, part=shaft[1]).report
    ovality = _feature(report, "body_ovality")
    assert ovality["verdict"] == "NotDecidable" and "all round" in ovality["error"]
    length = _feature(report, "length")
    assert length["verdict"] == "NotDecidable" and "could not be fitted" in length["error"]
    assert report["heads"] == [{"head": 0, "points": int(first.sum()), "part_points": int(first.sum())}]
    assert report["verdict"] == "NotDecidable"


def test_inspect_command_reads_the_head_property(shaft, tmp_path, capsys):
    field, _ = _scan(4)
    write_cloud(tmp_path / "field.ply", field)
    code = main(["inspect", "--field", str(tmp_path / "field.ply"), "--part", str(shaft[0]),
                 "--out", str(tmp_path / "report.json"), "--cold-cloud", str(tmp_path / "cold.ply")])
    assert code == 0
    out = capsys.readouterr().out
    assert "shaft-90x300: OK" in out and "heads: 0:" in out
    report = json.loads((tmp_path / "report.json").read_text())
    assert [entry["head"] for entry in report["heads"]] == [0, 1, 2, 3]
    cold = read_cloud(tmp_path / "cold.ply")
    assert np.array_equal(np.unique(cold["head"]), [0, 1, 2, 3])


def test_head_property_must_hold_head_indices():
    part = np.ones(3, dtype=bool)
    with pytest.raises(ValueError, match="must hold head indices \\(integers\\)"):
        head_points(np.array([0.0, 1.5, np.nan]), part)
    with pytest.raises(ValueError, match="0 or more"):
        head_points(np.array([0, -1, 2]), part)
    counted = head_points(np.array([2.0, 0.0, 2.0]), np.array([True, False, False]))
    assert [(h.head, h.points, h.part_points) for h in counted] == [(0, 1, 0), (2, 2, 1)]


def test_station_heads_see_both_ends():
    heads = station_heads()
    assert heads.shape == (4, 3) and np.allclose(np.linalg.norm(heads, axis=1), 700.0)
    assert np.all(np.sign(heads[:, 0]) == [1, -1, 1, -1])
