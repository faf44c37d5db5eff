"""``thermofield demo``: the embedded service end to end through its own HTTP API, as ``make demo`` runs it."""

import os
import signal
import socket
import subprocess
import sys
import time

import httpx
import numpy as np

from services.formats.ply import read_cloud


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_demo_scans_the_simulated_part_keeps_serving_and_stops_cleanly_on_ctrl_c(tmp_path):
    port = _free_port()
    demo = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "demo", "--data-dir", str(tmp_path / "data"),
         "--port", str(port), "--gateway-port", str(_free_port()), "--rerun-port", str(_free_port())],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    output = []
    deadline = time.monotonic() + 600
    try:
        for line in demo.stdout:
            output.append(line)
            if "Ctrl-C stops it" in line or time.monotonic() > deadline:
                break
        stdout = "".join(output)
        assert "keeps running" in stdout, stdout + demo.stderr.read()[-2000:] if demo.poll() is not None else stdout
        assert httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=10).status_code == 200, "still serving"
        os.killpg(demo.pid, signal.SIGINT)  # Ctrl-C in a terminal reaches the whole process group
        rest, stderr = demo.communicate(timeout=60)
    finally:
        if demo.poll() is None:
            os.killpg(demo.pid, signal.SIGKILL)
    stdout += rest
    assert demo.returncode == 0, stderr[-2000:]
    assert "job succeeded" in stdout and "temperature (deg C): min" in stdout
    assert "rerun --connect rerun+http://127.0.0.1:" in stdout
    assert "the service has stopped. Start it again with: thermofield serve --data-dir" in stdout
    field_files = list((tmp_path / "data").glob("*-field.ply"))
    assert len(field_files) == 1 and len(list((tmp_path / "data").glob("*-field.rrd"))) == 1
    field = read_cloud(field_files[0])
    hot = field["temperature"][np.isfinite(field["temperature"])]
    assert len(field["x"]) > 100_000 and hot.max() > 1000  # the forging is at up to about 1100 degrees C
    assert "Traceback" not in stderr
