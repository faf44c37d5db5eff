"""Faults of the station, scaled out (`thermofield gateway`, `api`, `worker` as separate processes on
PostgreSQL, RabbitMQ and Mosquitto): the device gateway lost in the middle of a capture, the artifact disk
filling while a scan stores its artifacts, the API killed during an upload. Each fault fails only what it
hit, cleanly, and the next request works."""

from __future__ import annotations

import hashlib
import os
import signal
import socket
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import psutil
import pytest
from sqlalchemy import text

from services.db.engine import make_engine
from services.formats.ply import read_cloud
from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig

pytestmark = [pytest.mark.integration, pytest.mark.postgres]

POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
SCAN_ARTIFACTS = ("cloud.ply", "field.ply", "field.rrd", "frames.npy", "thermal.npy")


def _wait_for(client: httpx.Client, job_id: str, reached, timeout_s: float = 300.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = client.get(f"/v1/jobs/{job_id}").json()
        if reached(state):
            return state
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not get there within {timeout_s} s: {state}")


def _finished(state: dict) -> bool:
    return state["status"] in ("succeeded", "failed")


def _assert_whole(client: httpx.Client, scan_id: str, directory: Path) -> None:
    """The scan's artifacts are all there and whole: each download's SHA-256 is its digest, the PLYs parse."""
    scan = client.get(f"/v1/scans/{scan_id}").json()
    artifacts = client.get(scan["links"]["job"]).json()["result"]["artifacts"]
    for name in SCAN_ARTIFACTS:
        content = client.get(f"/v1/scans/{scan_id}/{name}").content
        assert hashlib.sha256(content).hexdigest() == artifacts[name], name
        (directory / name).write_bytes(content)
    for name in ("cloud.ply", "field.ply"):
        assert len(read_cloud(directory / name)["x"]) == scan["summary"]["point_count"]


def _stored_bytes(artifact_dir: Path) -> int:
    return sum(path.stat().st_size for path in (artifact_dir / "sha256").glob("*/*"))


def _store_is_clean(artifact_dir: Path) -> None:
    assert not list((artifact_dir / "incoming").glob("*.part")), "a half-written blob is left in incoming/"


@pytest.mark.reliability  # minutes: five scans and three failing attempts (make test-reliability)
def test_a_lost_device_and_a_full_disk_fail_their_scan_cleanly_and_the_next_scan_works(small_disk, e2e, deployment,
                                                                                      tmp_path):
    artifact_dir = small_disk(1 << 30)
    min_free = 64 << 20
    env = {**deployment, "THERMOFIELD_ARTIFACT_DIR": str(artifact_dir), "THERMOFIELD_WORKER_PROCESSES": "1",
           "THERMOFIELD_MIN_FREE_BYTES": str(min_free),
           "THERMOFIELD_PROJECTOR_SETTLE_MS": "150"}  # a capture takes seconds, as with a real projector
    api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
    gateway = e2e.processes.start("gateway", ["gateway"], env)
    e2e.processes.start("api", ["api"], env)
    e2e.processes.start("worker", ["worker"], env)
    e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway")
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    admin = e2e.create_key(env, ["admin"])
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {admin}"}, timeout=60) as client:
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "true rig", "activate": "true"})
        assert created.status_code == 201, created.text

        # The gateway (and with it the devices) lost in the middle of a capture: that scan fails and says why.
        lost = client.post("/v1/scans", json={"part_id": "lost"}).json()
        _wait_for(client, lost["job_id"], lambda state: state["stage"] == "capture")
        time.sleep(1.5)  # the test's moment: well inside the capture (the gateway is filming its patterns; no
        # event says so)
        e2e.processes.stop(gateway, signal.SIGKILL)
        killed_at = time.monotonic()
        retrying = _wait_for(client, lost["job_id"], lambda state: state["stage"] == "retrying" or _finished(state))
        assert "capture failed: gateway" in retrying["error"] and "stopped answering during POST /v1/captures"             in retrying["error"], retrying  # the first attempt's error: lost in the middle of the capture
        failed = _wait_for(client, lost["job_id"], _finished, timeout_s=120)
        print(f"\ngateway killed mid-capture: attempt 1: {retrying['error']}; failed "
              f"{time.monotonic() - killed_at:.1f} s after the kill, after {failed['attempts']} attempts: {failed['error']}")
        assert failed["status"] == "failed", failed
        assert failed["error"].startswith("GatewayError: capture failed: gateway http://127.0.0.1:"), failed
        assert failed["attempts"] == 3, failed  # tried again twice (a device may come back), then failed
        scan = client.get(f"/v1/scans/{lost['scan_id']}").json()
        assert scan["status"] == "failed" and not any(name in scan["links"] for name in SCAN_ARTIFACTS)
        _store_is_clean(artifact_dir)

        # The gateway is back: the next scan works.
        e2e.processes.start("gateway-restarted", ["gateway"], env)
        e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway-restarted")
        after_loss = client.post("/v1/scans", json={"part_id": "after-loss"}).json()
        state = _wait_for(client, after_loss["job_id"], _finished)
        assert (state["status"], state["attempts"]) == ("succeeded", 1), state
        (tmp_path / "whole").mkdir()
        _assert_whole(client, after_loss["scan_id"], tmp_path / "whole")

        # The disk fills up: a scan's artifacts (~100 MB) no longer fit, though /readyz still saw room.
        filler = artifact_dir / "filler"
        with open(filler, "wb") as handle:  # another tenant of the disk leaves 16 MB more than /readyz wants
            os.posix_fallocate(handle.fileno(), 0, psutil.disk_usage(str(artifact_dir)).free - min_free - (16 << 20))
        assert client.get("/readyz").status_code == 200
        stored_before = _stored_bytes(artifact_dir)
        full = client.post("/v1/scans", json={"part_id": "full"}).json()
        failed = _wait_for(client, full["job_id"], _finished)
        assert failed["status"] == "failed" and failed["attempts"] == 1, failed  # no retry: it cannot help
        print(f"disk full while storing: {failed['error']}; readyz: {client.get('/readyz').json()['detail']}")
        assert failed["error"].startswith("StorageFull: [Errno 28] the artifact store at"), failed
        scan = client.get(f"/v1/scans/{full['scan_id']}").json()
        assert not any(name in scan["links"] for name in SCAN_ARTIFACTS), scan["links"]
        assert client.get(f"/v1/scans/{full['scan_id']}/field.ply").status_code == 404
        _store_is_clean(artifact_dir)
        orphaned = _stored_bytes(artifact_dir) - stored_before
        ready = client.get("/readyz")
        assert ready.status_code == 503 and "MB free" in ready.json()["detail"], ready.text
        assert int(ready.headers["retry-after"]) > 0
        _assert_whole(client, after_loss["scan_id"], tmp_path / "whole")  # what was stored before is intact

        filler.unlink()  # space again: ready, and the next scan works
        assert client.get("/readyz").status_code == 200
        state = _wait_for(client, client.post("/v1/scans").json()["job_id"], _finished)
        assert (state["status"], state["attempts"]) == ("succeeded", 1), state
        print(f"the failed scan left {orphaned / 1e6:.0f} MB of whole, unreferenced blobs (retention sweeps them)")


def _multipart_body(boundary: str, images: list[bytes]) -> list[bytes]:
    """A stereo upload as multipart/form-data parts, to be streamed chunk by chunk."""
    parts = [f'--{boundary}\r\nContent-Disposition: form-data; name="name"\r\n\r\nrecalibrated\r\n'.encode(),
             f'--{boundary}\r\nContent-Disposition: form-data; name="board"; filename="board.json"\r\n'
             'Content-Type: application/json\r\n\r\n'
             '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25}\r\n'.encode()]
    for field, prefix, image in [("reference_images", "c", images[0])] * 8 + [("device_images", "t", images[1])] * 8:
        parts.append(f'--{boundary}\r\nContent-Disposition: form-data; name="{field}"; '
                     f'filename="{prefix}.png"\r\nContent-Type: image/png\r\n\r\n'.encode() + image + b"\r\n")
    parts.append(f"--{boundary}--\r\n".encode())
    return parts


def _send_and_kill(e2e, api, port: int, request: bytes, delay_s: float) -> None:
    """Send ``request`` (all or part of an upload) and SIGKILL the API ``delay_s`` later, the request in flight."""
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(request)
        time.sleep(delay_s)  # the test's moment: the request in flight
        e2e.processes.stop(api, signal.SIGKILL)
        connection.settimeout(10)
        try:
            connection.recv(1 << 16)  # whatever came back, the client never saw its request through
        except ConnectionResetError:
            pass


def _blobs_are_whole(artifact_dir: Path) -> list[str]:
    """Every blob in the store is whole (its content hashes to its name); a crash left no .part visible."""
    blobs = sorted((artifact_dir / "sha256").glob("*/*"))
    for blob in blobs:
        assert hashlib.sha256(blob.read_bytes()).hexdigest() == blob.name, f"{blob} is partial"
    return [blob.name for blob in blobs]


def test_the_api_killed_during_an_upload_leaves_nothing_and_the_retry_succeeds(e2e, deployment, tmp_path):
    env = deployment
    port = int(env["THERMOFIELD_API_PORT"])
    api_url = f"http://127.0.0.1:{port}"
    api = e2e.processes.start("api", ["api"], env)
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    admin = e2e.create_key(env, ["admin"])
    headers = {"Authorization": f"Bearer {admin}"}
    with httpx.Client(base_url=api_url, headers=headers, timeout=60) as client:
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "true rig", "activate": "true"})
        calibration_id = created.json()["calibration_set_id"]
    rig = forging_rig()
    camera, thermal = rig.devices["camera"], rig.devices["thermal"]
    noise = np.random.default_rng(0).integers(0, 255, (camera.height, camera.width), dtype=np.uint8)
    images = [cv2.imencode(".png", noise)[1].tobytes(),  # incompressible: ~1 MB each, ~8 MB in all
              cv2.imencode(".png", np.zeros((thermal.height, thermal.width), np.uint16))[1].tobytes()]
    boundary = "thermofield-upload"
    body = b"".join(_multipart_body(boundary, images))
    path = f"/v1/calibration-sets/{calibration_id}/stereo"

    def request(key: str) -> bytes:
        return (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {admin}\r\n"
                f"Idempotency-Key: {key}\r\nContent-Type: multipart/form-data; boundary={boundary}\r\n"
                f"Content-Length: {len(body)}\r\n\r\n").encode() + body

    artifact_dir = Path(env["THERMOFIELD_ARTIFACT_DIR"])
    schema = env["THERMOFIELD_DATABASE_SCHEMA"]

    def rows() -> tuple[int, int]:
        with make_engine(POSTGRES_URL, schema).connect() as connection:
            return tuple(connection.execute(text(f"SELECT count(*) FROM {table}")).scalar_one()
                         for table in ("jobs", "idempotency_records"))

    # Half of the body sent, then the API SIGKILLed while it reads the rest: nothing at all is left.
    blobs_before = _blobs_are_whole(artifact_dir)  # the rig
    _send_and_kill(e2e, api, port, request("upload-0")[: len(body) // 2], 0.5)
    assert _blobs_are_whole(artifact_dir) == blobs_before and rows() == (0, 0)
    assert not list((artifact_dir / "incoming").glob("*.part"))
    # The whole body sent, the API SIGKILLed while it parses, checks and stores it: either all of it was
    # committed (job and idempotency record together) or none; no blob is ever partial.
    keys = ["upload-0"]
    for attempt, delay_s in enumerate((0.0, 0.15, 0.4, 1.0), start=1):
        api = e2e.processes.start(f"api-{attempt}", ["api"], env)
        e2e.processes.wait_until_healthy(f"{api_url}/readyz", f"api-{attempt}")
        keys.append(f"upload-{attempt}")
        _send_and_kill(e2e, api, port, request(keys[-1]), delay_s)
        jobs, records = rows()
        assert jobs == records <= attempt, (jobs, records)  # no job without its record, nor the reverse
        _blobs_are_whole(artifact_dir)
    committed = rows()[0]

    # The MES retries each request with its Idempotency-Key against the restarted API: each succeeds, once.
    e2e.processes.start("api-restarted", ["api"], env)
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api-restarted")
    answers = {}
    with httpx.Client(base_url=api_url, headers=headers, timeout=60) as client:
        for key in keys:
            for _ in range(2):
                retried = client.post(path, content=body, headers={
                    "Idempotency-Key": key, "Content-Type": f"multipart/form-data; boundary={boundary}"})
                assert retried.status_code == 202, retried.text
                assert answers.setdefault(key, retried.json()) == retried.json()  # the second is the replay
            job = client.get(answers[key]["links"]["job"]).json()
            assert job["kind"] == "calibrate" and job["status"] == "queued"
    assert rows() == (len(keys), len(keys)) and len({answer["job_id"] for answer in answers.values()}) == len(keys)
    print(f"\nAPI killed {len(keys)} times during an {len(body) / 1e6:.1f} MB upload: {committed} of the "
          f"{len(keys) - 1} whole requests had been committed; all {len(keys)} retries answered 202, one job each")
