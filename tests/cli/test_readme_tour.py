"""The README's quick tour, run as a newcomer would type it: from the projector patterns to a verdict."""

import json
import re
import shlex
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[2]


def _tour_commands() -> list[list[str]]:
    readme = (ROOT / "README.md").read_text()
    tour = readme.split("A quick tour without the service", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    return [shlex.split(line) for line in tour.replace("\\\n", " ").splitlines() if line.strip()]


def test_the_readme_tour_runs_from_patterns_to_a_verdict(tmp_path):
    commands = _tour_commands()
    assert [command[1] for command in commands] == ["patterns", "simulate", "field", "inspect"]
    for command in commands:
        command = [re.sub(r"^/tmp", str(tmp_path), part) for part in command]
        done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{shlex.join(command)}: {done.stderr}"
        assert "Traceback" not in done.stderr
    assert (tmp_path / "capture" / "thermal.tiff").is_file()
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["part"] == "forging-station-billet" and report["verdict"] in ("OK", "NotOK", "NotDecidable")
    diameters = {feature["name"]: feature for feature in report["features"]}
    # the simulated forging is its nominal, hot: each diameter comes back within its expanded uncertainty
    for name in ("body_diameter",):
        assert abs(diameters[name]["deviation"]) <= diameters[name]["uncertainty"], diameters[name]
