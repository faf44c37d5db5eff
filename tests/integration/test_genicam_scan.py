"""A scan through the service, scaled out (`thermofield gateway`, `api`, `worker` on PostgreSQL and RabbitMQ) and
embedded (`thermofield serve`), whose camera is a GigE Vision camera: Aravis' ``arv-fake-gv-camera-0.8`` on
loopback, driven by the genicam driver under software trigger; the thermal camera and the projector stay
simulated.

The fake camera does not see the projector: its frames are Aravis' diagonal ramp, whatever pattern is shown. So
this checks the capture path of a scan (settings, trigger, transfer, storage of the frames the camera sent),
not the reconstruction, whose accuracy tests/integration/test_embedded.py measures on the simulated station.
"""

from __future__ import annotations

import io
import time

import httpx
import numpy as np
import pytest

from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig
from tests.device_gateway.conftest import FakeGigEVisionCamera, _aravis_fake_ramp

pytestmark = pytest.mark.integration


def _finished(client: httpx.Client, job_id: str, timeout_s: float = 300.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = client.get(f"/v1/jobs/{job_id}").json()
        if state["status"] in ("succeeded", "failed"):
            return state
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish within {timeout_s} s: {state}")


def _scan_frames(client: httpx.Client) -> np.ndarray:
    """Scan once with the station's active calibration set to the true forging rig; the frames the scan stored."""
    devices = {device["name"]: device for device in client.get("/v1/devices").json()}
    assert (devices["camera"]["driver"], devices["camera"]["serial"]) == ("genicam", "GV01")
    created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                          data={"name": "true rig", "activate": "true"})
    assert created.status_code == 201, created.text
    accepted = client.post("/v1/scans", json={"part_id": "gige-1"})
    assert accepted.status_code == 202, accepted.text
    state = _finished(client, accepted.json()["job_id"])
    scan = client.get(f"/v1/scans/{accepted.json()['scan_id']}").json()
    print(f"\nscan of the fake GigE Vision camera's frames: {state['status']}, "
          f"{state.get('error') or scan.get('summary')}")
    # stored and processed through to its summary (the ramp's points lie anywhere: no accuracy to check)
    assert state["status"] == "succeeded" and scan["status"] == "succeeded", state
    return np.load(io.BytesIO(client.get(f"/v1/scans/{scan['scan_id']}/frames.npy").content))


def _assert_the_cameras_frames(frames: np.ndarray) -> None:
    assert len(frames) > 1 and frames.shape[1:] == (800, 1280) and frames.dtype == np.uint8
    # Each stored frame is one of the camera's, as it sent it (ramp, exposure 10 ms, gain 0): its top-left pixel
    # is its frame id modulo 255 (the ramp's shift), and the ids run one per pattern.
    ids = [int(frame[0, 0]) for frame in frames]
    assert all(np.array_equal(frame, _aravis_fake_ramp(1280, 800, frame_id, 10000, 0, 8))
               for frame, frame_id in zip(frames, ids))
    assert all((later - earlier) % 255 == 1 for earlier, later in zip(ids, ids[1:]))


CAMERA = {"THERMOFIELD_CAMERA_DRIVER": "genicam", "THERMOFIELD_CAMERA_EXPOSURE_US": "10000"}


def test_a_scan_captured_by_a_gigevision_camera_through_the_gateway_scaled_out(e2e, deployment):
    camera = FakeGigEVisionCamera().start()
    try:
        env = {**deployment, **CAMERA, "THERMOFIELD_WORKER_PROCESSES": "1",
               "THERMOFIELD_GENICAM_CAMERA": camera.address}
        api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
        e2e.processes.start("gateway", ["gateway"], env)
        e2e.processes.start("api", ["api"], env)
        e2e.processes.start("worker", ["worker"], env)
        e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway")
        e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
        assert "camera genicam, thermal simulated, projector simulated" in e2e.processes.log("gateway")
        admin = e2e.create_key(env, ["admin"])
        with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {admin}"}, timeout=60) as client:
            frames = _scan_frames(client)
    finally:
        camera.close()
    _assert_the_cameras_frames(frames)


def test_a_scan_captured_by_a_gigevision_camera_embedded(e2e, tmp_path):
    camera = FakeGigEVisionCamera().start()
    try:
        env = {**CAMERA, "THERMOFIELD_DATA_DIR": str(tmp_path / "data"), "THERMOFIELD_GENICAM_CAMERA": camera.address}
        port = e2e.free_port()
        e2e.processes.start("serve", ["serve", "--port", str(port), "--gateway-port", str(e2e.free_port()),
                                      "--rerun-port", str(e2e.free_port())], env)
        e2e.processes.wait_until_healthy(f"http://127.0.0.1:{port}/readyz", "serve")
        admin = e2e.create_key(env, ["admin"])
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                          timeout=60) as client:
            frames = _scan_frames(client)
    finally:
        camera.close()
    _assert_the_cameras_frames(frames)
