"""The gateway's HTTP API, served by uvicorn on a free port and used through its Python client."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import httpx
import numpy as np
import pytest
import uvicorn

from device_gateway.app import create_app
from device_gateway.client import GatewayClient, GatewayError
from device_gateway.station import Station
from device_gateway.transfer import MEDIA_TYPE

pytestmark = pytest.mark.integration


@contextmanager
def _serving(app, port: int) -> Iterator[str]:
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        assert time.monotonic() < deadline, "the gateway did not start"
        time.sleep(0.02)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10)


@pytest.fixture
def gateway(station, sequence_and_patterns, free_port) -> Iterator[GatewayClient]:
    with _serving(create_app(station, *sequence_and_patterns), free_port) as url, GatewayClient(url) as client:
        yield client


def test_health_and_devices(gateway, small_rig):
    assert gateway.health() == {"status": "ok", "devices": {"camera": True, "thermal": True, "projector": True}}
    devices = {device["name"]: device for device in gateway.devices()}
    assert set(devices) == {"camera", "thermal", "projector"}
    for name, device in devices.items():
        assert (device["width"], device["height"]) == small_rig.devices[name].size
        assert device["kind"] == small_rig.devices[name].kind
        assert device["driver"] == "simulated" and device["open"] is True


def test_capture_round_trip(gateway, sequence_and_patterns, small_rig, lit):
    sequence, patterns = sequence_and_patterns
    assert gateway.sequence() == sequence

    capture = gateway.capture(thermal_frames=2)

    camera, thermal = small_rig.devices["camera"], small_rig.devices["thermal"]
    assert capture.sequence == sequence
    assert capture.frames.shape == (len(patterns), camera.height, camera.width)
    assert capture.thermal.shape == (2, thermal.height, thermal.width)
    assert capture.frame_timestamps.shape == (len(patterns),)
    assert capture.thermal_metadata[0]["units"] == "degC"
    white = capture.frames[sequence.white_index].astype(float)
    black = capture.frames[sequence.black_index].astype(float)
    assert np.median((white - black)[lit]) > 40
    assert [device.kind for device in capture.devices] == ["camera", "thermal", "projector"]


def test_bad_capture_request_is_a_problem_document(gateway):
    response = httpx.post(f"{gateway.base_url}/v1/captures", json={"thermal_frames": 0})
    assert response.status_code == 422
    assert response.headers["content-type"] == "application/problem+json"
    assert "thermal_frames" in response.json()["detail"]
    with pytest.raises(GatewayError, match="thermal_frames") as error:
        gateway.capture(thermal_frames=0)
    assert error.value.status == 422


def test_request_bodies_over_the_limit_are_413_before_they_are_read(station, sequence_and_patterns):
    from fastapi.testclient import TestClient

    app = create_app(station, *sequence_and_patterns, max_body_bytes=1024)
    board = {"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25.0, "padding": "x" * 4096}
    nested = "[" * 2000 + "]" * 2000  # a nesting bomb, also longer than the limit
    with TestClient(app) as client:
        for path, body in (("/v1/captures", json.dumps({"thermal_frames": 1, "padding": "x" * 4096})),
                           ("/v1/board-views", json.dumps({"board": board, "views": 3})),
                           ("/v1/board-views", nested)):
            for chunked in (False, True):
                content = iter([body.encode()]) if chunked else body.encode()
                response = client.post(path, content=content, headers={"content-type": "application/json"})
                assert response.status_code == 413, (path, chunked, response.text)
                assert response.headers["content-type"] == "application/problem+json"
                assert "1024 bytes" in response.json()["detail"]
        small = client.post("/v1/board-views", json={"board": {"type": "chessboard"}, "views": 3})
        assert small.status_code == 422  # within the limit: read and validated


def test_empty_capture_request_takes_the_defaults(gateway, small_rig):
    response = httpx.post(f"{gateway.base_url}/v1/captures", timeout=30)
    assert response.status_code == 200
    assert response.headers["content-type"] == MEDIA_TYPE


def test_lost_device_answers_503_and_the_next_capture_works(simulated, unplugged, sequence_and_patterns, free_port):
    station = Station(unplugged(fail_at=3), simulated.thermal, simulated.projector)
    with _serving(create_app(station, *sequence_and_patterns), free_port) as url, GatewayClient(url) as client:
        response = httpx.post(f"{url}/v1/captures", json={})
        assert response.status_code == 503
        assert response.headers["content-type"] == "application/problem+json"
        assert "camera 'camera': connection lost" in response.json()["detail"]
        assert client.health()["status"] == "ok", "the camera was re-opened"
        assert client.capture().frames.shape[0] == len(sequence_and_patterns[1])


def test_unreachable_gateway_is_a_gateway_error(free_port):
    with GatewayClient(f"http://127.0.0.1:{free_port}", timeout_s=2) as client:
        with pytest.raises(GatewayError, match="unreachable"):
            client.health()


def test_a_gateway_that_dies_during_a_request_is_a_gateway_error_that_says_so(free_port):
    import socket

    with socket.socket() as server:  # what a gateway process killed mid-capture looks like to its client
        server.bind(("127.0.0.1", free_port))
        server.listen()

        def accept_then_die() -> None:
            connection, _ = server.accept()
            connection.recv(65536)
            connection.close()

        threading.Thread(target=accept_then_die, daemon=True).start()
        with GatewayClient(f"http://127.0.0.1:{free_port}", timeout_s=10) as client:
            with pytest.raises(GatewayError, match=r"stopped answering during POST /v1/captures \(the gateway or "
                                                   r"a device was lost\)"):
                client.capture()


def test_the_gateway_has_the_simulated_camera_render_its_sequence_before_serving(small_rig, sequence_and_patterns,
                                                                                   free_port):
    from device_gateway.drivers.simulated import SimulatedStation

    sequence, patterns = sequence_and_patterns
    simulated = SimulatedStation(rig=small_rig)
    station = Station(simulated.camera, simulated.thermal, simulated.projector)
    assert not simulated._clean_frames
    with _serving(create_app(station, sequence, patterns), free_port):
        assert len(simulated._clean_frames) == len({pattern.tobytes() for pattern in patterns})
