"""``thermofield demo``: the embedded service end to end through its own HTTP API, as ``make demo`` runs it."""

import socket
import subprocess
import sys

import numpy as np

from services.formats.ply import read_cloud


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_demo_scans_the_simulated_part_and_prints_the_field(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "services.cli.main", "demo", "--data-dir", str(tmp_path / "data"),
         "--port", str(_free_port()), "--gateway-port", str(_free_port()), "--rerun-port", str(_free_port())],
        capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "job succeeded" in result.stdout and "temperature (deg C): min" in result.stdout
    assert "rerun --connect rerun+http://127.0.0.1:" in result.stdout
    field_files = list((tmp_path / "data").glob("*-field.ply"))
    assert len(field_files) == 1 and len(list((tmp_path / "data").glob("*-field.rrd"))) == 1
    field = read_cloud(field_files[0])
    hot = field["temperature"][np.isfinite(field["temperature"])]
    assert len(field["x"]) > 100_000 and hot.max() > 1000  # the forging is at up to about 1100 degrees C
    assert "Traceback" not in result.stderr
