"""End to end over HTTP, scaled out: `thermofield api`, `thermofield worker` (two spawned processes),
`thermofield gateway` as separate processes on PostgreSQL, RabbitMQ and Mosquitto, a shared artifact
directory, as in docker/ (configured only by environment variables)."""

import signal
import subprocess
import time
import uuid

import httpx
import pytest
from sqlalchemy import text

from services.db.engine import make_engine
from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig

POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
BROKER_URL = "amqp://guest:guest@127.0.0.1:5672"


@pytest.fixture
def deployment(e2e, tmp_path):
    """Environment of one isolated deployment: its own PostgreSQL schema, job queue and MQTT site."""
    tag = uuid.uuid4().hex[:10]
    api_port, gateway_port = e2e.free_port(), e2e.free_port()
    env = {
        "THERMOFIELD_DATABASE_URL": POSTGRES_URL,
        "THERMOFIELD_DATABASE_SCHEMA": f"tf_it_{tag}",
        "THERMOFIELD_BROKER_URL": BROKER_URL,
        "THERMOFIELD_JOB_QUEUE": f"tf-it-{tag}",
        "THERMOFIELD_ARTIFACT_DIR": str(tmp_path / "artifacts"),
        "THERMOFIELD_GATEWAY_URL": f"http://127.0.0.1:{gateway_port}",
        "THERMOFIELD_GATEWAY_PORT": str(gateway_port),
        "THERMOFIELD_API_PORT": str(api_port),
        "THERMOFIELD_RERUN_PORT": str(e2e.free_port()),
        "THERMOFIELD_SITE": f"it-{tag}",
        "THERMOFIELD_WORKER_PROCESSES": "2",
    }
    yield env
    with make_engine(POSTGRES_URL).begin() as connection:
        connection.execute(text(f"DROP SCHEMA IF EXISTS tf_it_{tag} CASCADE"))
    _delete_queues(env["THERMOFIELD_JOB_QUEUE"])


def _delete_queues(queue: str) -> None:
    import pika

    connection = pika.BlockingConnection(pika.URLParameters(BROKER_URL))
    channel = connection.channel()
    for name in (queue, f"{queue}.DQ", f"{queue}.XQ"):
        channel.queue_delete(name)
    connection.close()


def test_scaled_out_scans_with_two_workers_and_survive_a_worker_crash(e2e, deployment, tmp_path):
    env = deployment
    api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
    e2e.processes.start("gateway", ["gateway"], env)
    e2e.processes.start("api", ["api"], env)
    worker = e2e.processes.start("worker", ["worker"], env)
    e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway")
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    admin = e2e.create_key(env, ["admin"])
    events = e2e.mqtt(f"{env['THERMOFIELD_SITE']}/station1")

    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {admin}"}, timeout=30) as client:
        assert client.post("/v1/scans").status_code == 409  # nothing is active before a calibration set exists
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "true rig", "activate": "true"})
        assert created.status_code == 201, created.text

        jobs = [client.post("/v1/scans", json={"part_id": f"part-{i}"}).json() for i in range(2)]
        workers = set()
        for job in jobs:
            final = e2e.follow_events(client, job["job_id"])[-1]
            assert final[0] == "done" and final[1]["status"] == "succeeded", (final, e2e.processes.log("worker"))
            workers.add(final[1]["worker"])
        assert len(workers) == 2, workers  # the two scans ran at once, one in each spawned worker process
        scan = client.get(f"/v1/scans/{jobs[0]['scan_id']}").json()
        (tmp_path / "field.ply").write_bytes(client.get(scan["links"]["field.ply"]).content)
        assert scan["summary"]["temperature"]["max"] > 900

        # A worker killed in the middle of a scan: RabbitMQ redelivers the unacknowledged message to a
        # restarted worker, which runs the job again (attempt 2) to success.
        accepted = client.post("/v1/scans", headers={"Idempotency-Key": "crash-1"}).json()
        _wait_for_stage(client, accepted["job_id"], lambda state: state["status"] == "running")
        e2e.processes.stop(worker, signal.SIGKILL)
        e2e.processes.start("worker-restarted", ["worker"], env)
        final = e2e.follow_events(client, accepted["job_id"])[-1][1]
        assert final["status"] == "succeeded" and final["attempts"] == 2, final
        assert client.post("/v1/scans", headers={"Idempotency-Key": "crash-1"}).json() == accepted

    errors = e2e.field_errors(tmp_path / "field.ply")
    assert errors["median_distance_mm"] < 0.5, errors
    assert errors["median_temperature_error_k"] < 1.0, errors
    assert events.states(f"{env['THERMOFIELD_SITE']}/station1/scans/{jobs[1]['scan_id']}")[-1]["status"] == "succeeded"


def _wait_for_stage(client: httpx.Client, job_id: str, reached, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if reached(client.get(f"/v1/jobs/{job_id}").json()):
            return
        time.sleep(0.05)
    raise AssertionError(f"job {job_id} did not start within {timeout_s} s")


def test_api_and_worker_refuse_to_start_without_a_broker(tmp_path):
    import os
    import sys

    for command in ("api", "worker"):
        result = subprocess.run([sys.executable, "-m", "services.cli.main", command],
                                env=os.environ | {"THERMOFIELD_DATA_DIR": str(tmp_path)}, capture_output=True,
                                text=True, timeout=120)
        assert result.returncode == 2
        assert "THERMOFIELD_BROKER_URL" in result.stderr and "Traceback" not in result.stderr
