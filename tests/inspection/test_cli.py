"""``thermofield inspect`` end to end: the report, the clouds, the picture, and one-line errors for bad input."""

import json

import numpy as np
import pytest

from services.cli.main import main
from services.formats.ply import read_cloud, write_cloud

pytestmark = pytest.mark.integration


def test_inspect_command_writes_report_and_clouds(station, tmp_path, capsys):
    field, _ = station.scan(seed=7)
    write_cloud(tmp_path / "field.ply", field)
    code = main(["inspect", "--field", str(tmp_path / "field.ply"), "--part", str(station.part_path),
                 "--out", str(tmp_path / "report.json"), "--cold-cloud", str(tmp_path / "cold.ply"),
                 "--deviation", str(tmp_path / "deviation.ply"), "--picture", str(tmp_path / "deviation.png")])
    assert code == 0
    assert "billet-90: OK" in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["version"] == 1 and report["verdict"] == "OK"
    feature = report["features"][0]
    assert {"name", "hot", "cold", "nominal", "deviation", "uncertainty", "verdict"} <= set(feature)
    assert np.asarray(report["alignment"]["matrix"]).shape == (4, 4)
    assert {"mean", "std", "min", "max", "fraction_outside"} <= set(report["surface"])
    deviation = read_cloud(tmp_path / "deviation.ply")
    assert len(deviation["x"]) == len(field["x"]) and deviation["deviation"].dtype == np.float32
    assert np.nanmax(np.abs(deviation["deviation"])) < 0.5
    cold = read_cloud(tmp_path / "cold.ply")
    assert {"temperature_fallback", "deviation", "red"} <= set(cold)
    assert (tmp_path / "deviation.png").stat().st_size > 10000


def test_bad_input_exits_2_with_one_line(station, tmp_path, capsys):
    field, _ = station.scan(seed=8)
    write_cloud(tmp_path / "cloud.ply", {name: field[name] for name in ("x", "y", "z")})
    out = str(tmp_path / "report.json")
    assert main(["inspect", "--field", str(tmp_path / "cloud.ply"), "--part", str(station.part_path),
                 "--out", out]) == 2
    error = capsys.readouterr().err
    assert "cloud.ply: The field lacks the properties ['temperature']" in error and "Traceback" not in error
    assert main(["inspect", "--field", str(tmp_path / "absent.ply"), "--part", str(station.part_path),
                 "--out", out]) == 2
    assert "point cloud file is missing" in capsys.readouterr().err
    assert main(["inspect", "--field", str(tmp_path / "cloud.ply"), "--part", str(tmp_path / "none.json"),
                 "--out", out]) == 2
    assert "cannot read the part file" in capsys.readouterr().err
    part = json.loads(station.part_path.read_text())
    part["features"][0]["region"] = {"min": [500, 500, 500], "max": [501, 501, 501]}
    (station.part_path.parent / "far.json").write_text(json.dumps(part))
    assert main(["inspect", "--field", str(tmp_path / "cloud.ply"), "--part",
                 str(station.part_path.parent / "far.json"), "--out", out]) == 2
    assert "does the box enclose the surface" in capsys.readouterr().err
    assert not (tmp_path / "report.json").exists()
