"""The GenICam driver and ``thermofield gateway`` against a real GigE Vision peer with no hardware:
``arv-fake-gv-camera-0.8`` on loopback (GVCP control, GVSP stream; it honours the software trigger and sends
nothing on a line trigger, no pulse coming). The camera is opened by its IP address, which connects to it
directly: a search by id would broadcast discovery on every network of the machine.

The fake camera does not see the projector: its images are Aravis' diagonal ramp (see ``aravis_fake_ramp``), so
these tests check the capture path (trigger, transfer, depth, exposure, timestamps, faults), not what the
patterns look like on a part.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from device_gateway.client import GatewayClient
from device_gateway.devices import DeviceLost
from device_gateway.drivers.genicam import GenicamCamera

pytestmark = pytest.mark.integration

WIDTH, HEIGHT = 1280, 800


def test_one_frame_per_software_trigger_and_none_without(fake_gv_camera, aravis_fake_ramp):
    camera = GenicamCamera(device_id=fake_gv_camera.address, pixel_format="Mono16", exposure_us=20000,
                           region=(0, 0, 320, 200))
    camera.open()
    try:
        assert (camera.info.model, camera.info.serial) == ("Aravis Fake", "GV01")
        time.sleep(0.3)  # a free-running camera would queue frames now
        frames = [camera.grab(timeout_s=2.0) for _ in range(3)]
    finally:
        camera.close()
    ids = [frame.metadata["frame_id"] for frame in frames]
    assert ids == [ids[0], ids[0] + 1, ids[0] + 2], "exactly one frame per trigger"
    for frame in frames:
        assert frame.image.dtype == np.uint16
        np.testing.assert_array_equal(frame.image, aravis_fake_ramp(320, 200, frame.metadata["frame_id"], 20000, 0, 16))


def test_a_line_trigger_without_a_pulse_is_a_lost_camera_named(fake_gv_camera):
    camera = GenicamCamera(device_id=fake_gv_camera.address, trigger="Line0", region=(0, 0, 64, 48))
    camera.open()
    with pytest.raises(DeviceLost, match=r"camera 'camera' \(GenICam 127.0.0.1\): no frame within 0.5 s "
                                         r"\(Line0 trigger\)"):
        camera.grab(timeout_s=0.5)
    assert not camera.is_open


def test_lost_packets_are_a_lost_camera_named(lossy_gv_camera):
    camera = GenicamCamera(device_id=lossy_gv_camera.address, region=(0, 0, 640, 400))
    camera.open()
    with pytest.raises(DeviceLost, match=r"camera 'camera' \(GenICam 127.0.0.1\): frame \d+ arrived incomplete"):
        for _ in range(5):  # 30 % of a frame's ~180 packets are dropped: the first frame is all but sure to lose some
            camera.grab(timeout_s=2.0)
    assert not camera.is_open


def _start_gateway(port: int, extra: dict[str, str]) -> subprocess.Popen:
    environment = {key: value for key, value in os.environ.items() if not key.startswith("THERMOFIELD_")}
    environment.update({
        "THERMOFIELD_CAMERA_DRIVER": "genicam", "THERMOFIELD_GENICAM_CAMERA": "127.0.0.1",
        "THERMOFIELD_CAMERA_EXPOSURE_US": "20000", "THERMOFIELD_CAMERA_GAIN": "1",
        "THERMOFIELD_THERMAL_DRIVER": "genicam", "THERMOFIELD_GENICAM_THERMAL": "Fake_1",
        "THERMOFIELD_GENICAM_THERMAL_KELVIN_PER_COUNT": "0.01", **extra})
    process = subprocess.Popen([sys.executable, "-m", "services.cli.main", "gateway", "--projector-driver",
                                "simulated", "--port", str(port)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=environment)
    deadline = time.monotonic() + 60
    while True:
        assert process.poll() is None, process.stderr.read()
        try:
            httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2)
            return process
        except httpx.HTTPError:
            assert time.monotonic() < deadline, "the gateway did not start"
            time.sleep(0.2)


def _stop(process: subprocess.Popen) -> str:
    process.terminate()
    output, errors = process.communicate(timeout=30)
    return output + errors


def test_the_gateway_captures_a_sequence_with_the_genicam_cameras(fake_gv_camera, free_port, aravis_fake_ramp):
    # 16-bit frames, kept at their depth through the capture archive (Mono8: tests/integration/test_genicam_scan.py)
    process = _start_gateway(free_port, {"THERMOFIELD_GENICAM_PIXEL_FORMAT": "Mono16"})
    try:
        with GatewayClient(f"http://127.0.0.1:{free_port}") as client:
            assert client.health() == {"status": "ok", "devices": {"camera": True, "thermal": True,
                                                                   "projector": True}}
            devices = {device["name"]: device for device in client.devices()}
            assert (devices["camera"]["driver"], devices["camera"]["model"], devices["camera"]["serial"]) == (
                "genicam", "Aravis Fake", "GV01")
            assert (devices["camera"]["width"], devices["camera"]["height"]) == (WIDTH, HEIGHT)
            assert devices["thermal"]["driver"] == "genicam" and devices["projector"]["driver"] == "simulated"
            sequence = client.sequence()
            requested = time.time()
            capture = client.capture()
            answered = time.time()
    finally:
        output = _stop(process)
    assert "camera genicam, thermal genicam, projector simulated" in output

    assert capture.frames.shape == (len(sequence.frames), HEIGHT, WIDTH) and capture.frames.dtype == np.uint16
    ids = [metadata["frame_id"] for metadata in capture.frame_metadata]
    assert ids == list(range(ids[0], ids[0] + len(ids))), "one triggered frame per pattern, in order"
    for frame, metadata in zip(capture.frames, capture.frame_metadata):  # the exposure and gain set: 20 ms, 1
        np.testing.assert_array_equal(frame, aravis_fake_ramp(WIDTH, HEIGHT, metadata["frame_id"], 20000, 1, 16))
    assert capture.exposure["exposures_us"] == [20000] and capture.exposure["saturation_level"] == 65535
    assert {metadata["pixel_format"] for metadata in capture.frame_metadata} == {"Mono16"}
    stamps = capture.frame_timestamps
    assert requested <= stamps[0] and stamps[-1] <= answered and np.all(np.diff(stamps) > 0)
    camera_s = np.array([metadata["camera_timestamp_ns"] for metadata in capture.frame_metadata]) / 1e9
    np.testing.assert_allclose(np.diff(stamps), np.diff(camera_s), atol=1e-6)  # the camera's own intervals

    thermal, metadata = capture.thermal[0], capture.thermal_metadata[0]
    counts = aravis_fake_ramp(512, 512, metadata["frame_id"], 10000, 0, 16)
    np.testing.assert_allclose(thermal, counts * 0.01 - 273.15, atol=1e-3)
    assert metadata["units"] == "degC" and capture.thermal_timestamps[0] >= stamps[-1]


@pytest.mark.reliability  # a fault test (about 20 s): in make test-reliability, as the service's other faults are
def test_a_camera_killed_mid_sequence_fails_that_capture_naming_it_and_comes_back(fake_gv_camera, free_port):
    # 100 ms per pattern: a sequence takes seconds, the camera is killed a second into it.
    process = _start_gateway(free_port, {"THERMOFIELD_PROJECTOR_SETTLE_MS": "100",
                                         "THERMOFIELD_THERMAL_DRIVER": "simulated"})
    url = f"http://127.0.0.1:{free_port}"
    try:
        with GatewayClient(url) as client:
            sequence = client.sequence()
        answer: dict[str, httpx.Response] = {}
        capturing = threading.Thread(target=lambda: answer.update(
            response=httpx.post(f"{url}/v1/captures", json={}, timeout=60)))
        capturing.start()
        time.sleep(1.0)  # the test's moment: the camera vanishes while the gateway films (no event says so)
        fake_gv_camera.kill()
        capturing.join(timeout=60)
        response = answer["response"]
        assert response.status_code == 503
        assert response.headers["content-type"] == "application/problem+json"
        detail = response.json()["detail"]
        assert "camera 'camera' (GenICam 127.0.0.1)" in detail
        delivered = int(re.search(r"after (\d+) frames since it was opened", detail).group(1))
        assert 0 < delivered < len(sequence.frames), f"killed mid-sequence: {detail}"
        print(f"\ncamera killed mid-sequence ({len(sequence.frames)} patterns): 503 {detail}")
        with GatewayClient(url) as client:
            assert client.health()["devices"] == {"camera": False, "thermal": True, "projector": True}
            fake_gv_camera.start()  # plugged in again: the next capture re-opens it
            capture = client.capture()
            assert capture.frames.shape[1:] == (HEIGHT, WIDTH)
            assert client.health()["status"] == "ok"
    finally:
        _stop(process)


@pytest.mark.reliability  # a fault test (about 14 s): in make test-reliability
def test_a_camera_that_vanishes_between_captures_is_seen_closed_and_its_next_grab_lost(fake_gv_camera):
    camera = GenicamCamera(device_id=fake_gv_camera.address, region=(0, 0, 64, 48))
    camera.open()
    camera.grab(timeout_s=2.0)
    fake_gv_camera.kill()
    deadline = time.monotonic() + 30
    while camera.is_open:  # Aravis' heartbeat notices the silent control channel (its control-lost signal)
        assert time.monotonic() < deadline, "the vanished camera still looks open"
        time.sleep(0.1)
    with pytest.raises(DeviceLost, match=r"camera 'camera' \(GenICam 127.0.0.1\): its control channel was lost"):
        camera.grab(timeout_s=2.0)


def test_metered_exposure_is_set_on_the_camera_between_frames(fake_gv_camera, simulated, sequence_and_patterns,
                                                               aravis_fake_ramp):
    from device_gateway.station import ExposureControl, Station

    camera = GenicamCamera(device_id=fake_gv_camera.address, exposure_us=20000, region=(0, 0, 160, 100))
    station = Station(camera, simulated.thermal, simulated.projector)
    sequence, patterns = sequence_and_patterns
    try:
        capture = station.capture(sequence, patterns, exposure=ExposureControl(mode="auto"))
    finally:
        station.close()
    (chosen,) = capture.exposure["exposures_us"]
    assert chosen < 20000, "the ramp saturates at 20 ms: metering shortens it"
    for frame, metadata in zip(capture.frames, capture.frame_metadata):
        assert metadata["exposure_us"] == int(chosen)  # the camera's exposure register counts whole microseconds
        np.testing.assert_array_equal(frame, aravis_fake_ramp(160, 100, metadata["frame_id"], int(chosen), 0, 8))
