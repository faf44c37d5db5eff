"""``thermofield gateway`` as a process: with no OAK attached it still serves, and says why it cannot capture."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import httpx
import pytest

from services.cli.main import main

pytestmark = pytest.mark.integration


def test_gateway_without_hardware_reports_degraded_health_and_refuses_captures(free_port):
    port = free_port
    environment = {key: value for key, value in os.environ.items() if key not in ("DISPLAY", "WAYLAND_DISPLAY")}
    process = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "gateway", "--driver", "oak", "--host", "127.0.0.1",
         "--port", str(port)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=environment,
    )
    try:
        deadline = time.monotonic() + 60
        while True:
            assert process.poll() is None, process.stderr.read()
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2)
                break
            except httpx.HTTPError:
                assert time.monotonic() < deadline, "the gateway did not start"
                time.sleep(0.2)
        assert health.status_code == 503
        assert health.json()["status"] == "degraded"
        assert set(health.json()["devices"]) == {"camera", "thermal", "projector"}
        capture = httpx.post(f"http://127.0.0.1:{port}/v1/captures", json={}, timeout=30)
        assert capture.status_code == 503
        assert capture.headers["content-type"] == "application/problem+json"
        assert "no OAK device is connected" in capture.json()["detail"]
    finally:
        process.terminate()
        output, _ = process.communicate(timeout=20)
    assert f"http://127.0.0.1:{port}" in output


def test_unknown_driver_is_refused(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["gateway", "--driver", "webcam"])
    assert exit_.value.code == 2
    assert "invalid choice: 'webcam'" in capsys.readouterr().err


def test_driver_stands_for_every_device_whose_own_driver_is_not_chosen(monkeypatch):
    import argparse

    from services.cli.gateway import register, settings_of

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    drivers = lambda *arguments: tuple(settings_of(parser.parse_args(["gateway", *arguments])).station_drivers)  # noqa: E731
    assert drivers("--driver", "oak") == ("oak", "oak", "display")
    monkeypatch.setenv("THERMOFIELD_CAMERA_DRIVER", "genicam")
    assert drivers() == ("genicam", "simulated", "simulated")
    assert drivers("--driver", "simulated") == ("genicam", "simulated", "simulated")  # as `thermofield serve` starts it
    assert drivers("--driver", "oak", "--thermal-driver", "genicam") == ("genicam", "genicam", "display")
    assert drivers("--driver", "oak", "--camera-driver", "simulated", "--projector-driver", "simulated") == (
        "simulated", "oak", "simulated")
