"""End to end over HTTP, embedded: `thermofield serve` (SQLite, in-process worker, simulated gateway,
Rerun proxy) as one process; keys from `thermofield apikey create`; events over SSE and MQTT; recovery
of the job a crash interrupted."""

import io
import signal
import time
import uuid

import cv2
import httpx
import numpy as np
import tifffile

from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig


def test_embedded_scan_from_http_to_an_accurate_field(e2e, tmp_path):
    site = f"it-{uuid.uuid4().hex[:8]}"
    env = {"THERMOFIELD_DATA_DIR": str(tmp_path / "data"), "THERMOFIELD_SITE": site}
    port = e2e.free_port()
    restart_arguments = ["serve", "--port", str(port), "--gateway-port", str(e2e.free_port()),
                         "--rerun-port", str(e2e.free_port())]
    e2e.processes.start("serve", restart_arguments, env)
    e2e.processes.wait_until_healthy(f"http://127.0.0.1:{port}/readyz", "serve")
    assert f"http://127.0.0.1:{port}" in e2e.processes.log("serve")
    admin = e2e.create_key(env, ["admin"])
    events = e2e.mqtt(f"{site}/station1")

    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                      timeout=30) as client:
        assert client.get("/v1/calibration-sets").json()[0]["source"] == "simulator"  # active out of the box
        assert {d["name"] for d in client.get("/v1/devices").json()} == {"camera", "thermal", "projector"}
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "uploaded true rig", "activate": "true"})
        assert created.status_code == 201, created.text

        accepted = client.post("/v1/scans", json={"part_id": "billet-1"}, headers={"Idempotency-Key": "k1"})
        assert accepted.status_code == 202, accepted.text
        scan_id, job_id = accepted.json()["scan_id"], accepted.json()["job_id"]
        progress = e2e.follow_events(client, job_id)
        assert progress[-1][0] == "done" and progress[-1][1]["status"] == "succeeded", progress[-1]
        stages = [state["stage"] for _, state in progress]
        assert [s for s in ("capture", "reconstruct", "fuse", "store", "stream") if s in stages], stages

        scan = client.get(f"/v1/scans/{scan_id}").json()
        assert scan["calibration_set_id"] == created.json()["calibration_set_id"]
        summary = scan["summary"]
        assert summary["point_count"] > 100_000 and summary["points_with_temperature"] > 50_000
        assert 900 < summary["temperature"]["max"] < 1200  # the simulated part is up to ~1100 C
        (tmp_path / "field.ply").write_bytes(client.get(scan["links"]["field.ply"]).content)
        assert client.get(scan["links"]["field.rrd"]).content[:4] == b"RRF2"
        frame = cv2.imdecode(np.frombuffer(client.get(scan["links"]["frames"].format(index=0)).content, np.uint8),
                             cv2.IMREAD_UNCHANGED)
        assert frame.shape == (800, 1280)
        thermal = tifffile.imread(io.BytesIO(client.get(scan["links"]["thermal"].format(index=0)).content))
        assert thermal.shape == (256, 320) and thermal.dtype == np.float32 and np.nanmax(thermal) > 900

        # One step again on the stored scan: reconstruct, fuse that cloud; register thermal onto camera.
        reconstructed = client.post(f"/v1/scans/{scan_id}/jobs", json={"kind": "reconstruct"}).json()["job_id"]
        registered = client.post(f"/v1/scans/{scan_id}/jobs", json={"kind": "register"}).json()["job_id"]
        assert e2e.follow_events(client, reconstructed)[-1][1]["status"] == "succeeded"
        fused = client.post(f"/v1/scans/{scan_id}/jobs", json={"kind": "fuse", "cloud_job_id": reconstructed})
        fuse_state = e2e.follow_events(client, fused.json()["job_id"])[-1][1]
        assert fuse_state["status"] == "succeeded", fuse_state
        assert fuse_state["result"]["summary"]["point_count"] == summary["point_count"]  # same frames, same rig
        register_state = e2e.follow_events(client, registered)[-1][1]
        assert register_state["status"] == "succeeded", register_state
        registration = client.get(f"/v1/jobs/{registered}/artifacts/registration.json").json()
        assert registration["model"] == "similarity" and registration["nmi"] > 0

    # Crash recovery: the serve process is killed in the middle of a scan; on restart the job that was
    # running is queued again and runs to success as its second attempt.
    serve_command = e2e.processes.running[0][1]
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                      timeout=30) as client:
        interrupted = client.post("/v1/scans").json()["job_id"]
        deadline = time.monotonic() + 120
        while client.get(f"/v1/jobs/{interrupted}").json()["status"] != "running" and time.monotonic() < deadline:
            time.sleep(0.05)
    e2e.processes.stop(serve_command, signal.SIGKILL)
    e2e.processes.start("serve-restarted", restart_arguments, env)
    e2e.processes.wait_until_healthy(f"http://127.0.0.1:{port}/readyz", "serve-restarted")
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {admin}"},
                      timeout=30) as client:
        final = e2e.follow_events(client, interrupted)[-1][1]
    assert (final["status"], final["attempts"]) == ("succeeded", 2), final
    serve = dict(e2e.processes.running)["serve-restarted"]
    assert e2e.listening_addresses(serve) <= {"127.0.0.1"}  # API, gateway and Rerun proxy on loopback by default
    e2e.processes.assert_no_secrets_in_logs([admin])

    errors = e2e.field_errors(tmp_path / "field.ply")
    assert errors["median_distance_mm"] < 0.5, errors
    assert errors["median_temperature_error_k"] < 1.0, errors
    assert errors["hidden_points_nan"] > 0.95, errors

    scan_states = events.states(f"{site}/station1/scans/{scan_id}")
    assert scan_states[-1]["status"] == "succeeded"
    assert scan_states[-1]["summary"]["point_count"] == summary["point_count"]
    assert [state["status"] for state in events.states(f"{site}/station1/jobs/{job_id}")][0] == "queued"
