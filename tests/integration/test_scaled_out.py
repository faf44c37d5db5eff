"""End to end over HTTP, scaled out: `thermofield api`, `thermofield worker` (two spawned processes),
`thermofield gateway` as separate processes on PostgreSQL, RabbitMQ and Mosquitto, a shared artifact
directory, as in docker/ (configured only by environment variables). A worker SIGKILLed in the middle of
a scan: the scan is finished exactly once by a restarted worker, its artifacts whole, its MQTT states in
order. The API's OPC UA server hears of the workers' results over MQTT, and an MES (asyncua, signed and
encrypted) prepares a recipe, starts a scan a worker inspects, and reads the verdict HTTP gives."""

import asyncio
import hashlib
import signal
import subprocess
import threading
import time

import httpx
import numpy as np
import psutil
import pytest
from services.formats.ply import read_cloud
from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig
from asyncua import ua
from services.simulation.hot_part import write_forging_part
from tests.opcua.mes import Mes, client_certificate, value

pytestmark = [pytest.mark.integration, pytest.mark.postgres]


@pytest.mark.reliability  # 1.5 min: in make test-reliability (also in .ci/run), not make test
def test_scaled_out_scans_with_two_workers_and_survive_a_worker_crash(e2e, deployment, tmp_path):
    env = deployment
    api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
    opcua = f"opc.tcp://127.0.0.1:{e2e.free_port()}/thermofield"
    e2e.processes.start("gateway", ["gateway"], env)
    e2e.processes.start("api", ["api"], env | {"THERMOFIELD_OPCUA_ENDPOINT": opcua,
                                               "THERMOFIELD_OPCUA_PKI_DIR": str(tmp_path / "opcua")})
    worker = e2e.processes.start("worker", ["worker"], env)
    e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway")
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    admin = e2e.create_key(env, ["admin"])
    events = e2e.mqtt(f"{env['THERMOFIELD_SITE']}/station1")
    results = _ResultReadyListener(opcua, admin, tmp_path)

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
        assert results.wait_for(2), results.received
        assert sorted((r["ResultId"], r["PartId"], r["ResultState"]) for r in results.received[:2]) == sorted(
            (job["scan_id"], f"part-{i}", 1) for i, job in enumerate(jobs))  # 1: Completed
        results.close()
        scan = client.get(f"/v1/scans/{jobs[0]['scan_id']}").json()
        (tmp_path / "field.ply").write_bytes(client.get(scan["links"]["field.ply"]).content)
        assert scan["summary"]["temperature"]["max"] > 900

        # A worker killed in the middle of a scan: RabbitMQ redelivers the unacknowledged message to a
        # restarted worker, which runs the job again (attempt 2) to success.
        accepted = client.post("/v1/scans", headers={"Idempotency-Key": "crash-1"}).json()
        _wait_for_stage(client, accepted["job_id"], lambda state: state["status"] == "running")
        e2e.processes.stop(worker, signal.SIGKILL)
        restarted = e2e.processes.start("worker-restarted", ["worker"], env)
        final = e2e.follow_events(client, accepted["job_id"])[-1][1]
        assert final["status"] == "succeeded" and final["attempts"] == 2, final
        assert client.post("/v1/scans", headers={"Idempotency-Key": "crash-1"}).json() == accepted
        # Finished exactly once: one set of artifacts, the scan's and the job's, each whole.
        crashed = client.get(f"/v1/scans/{accepted['scan_id']}").json()
        artifacts = final["result"]["artifacts"]
        assert {name for name in crashed["links"] if name.endswith((".ply", ".rrd", ".npy"))} <= set(artifacts)
        for name in ("cloud.ply", "field.ply", "field.rrd", "frames.npy", "thermal.npy"):
            content = client.get(f"/v1/scans/{accepted['scan_id']}/{name}").content
            assert hashlib.sha256(content).hexdigest() == artifacts[name], name
            (tmp_path / f"crashed-{name}").write_bytes(content)
        for name in ("cloud.ply", "field.ply"):
            assert len(read_cloud(tmp_path / f"crashed-{name}")["x"]) == crashed["summary"]["point_count"]
        assert np.load(tmp_path / "crashed-frames.npy", allow_pickle=False).ndim == 3
        topic = f"{env['THERMOFIELD_SITE']}/station1/jobs/{accepted['job_id']}"
        deadline = time.monotonic() + 30  # the job's last MQTT message arrives
        while not any(state["status"] == "succeeded" for state in events.states(topic)):
            assert time.monotonic() < deadline, events.states(topic)
            time.sleep(0.1)
        states = events.states(topic)
        _assert_in_order(states)
        assert [state["status"] for state in states].count("succeeded") == 1, states
        assert {state["attempts"] for state in states} == {0, 1, 2}, states  # queued, the killed run, the rerun

        # The MES: a part type uploaded over HTTP is its recipe; prepared and started over OPC UA, the scan runs in
        # a worker process, is inspected, and its ResultReady and GetResultById give the verdict HTTP gives.
        part_file = write_forging_part(tmp_path / "part")
        part_type = client.post("/v1/part-types", files={
            "part": ("part.json", part_file.read_bytes()),
            "mesh": ("forging.stl", (part_file.parent / "forging.stl").read_bytes())})
        assert part_type.status_code == 201, part_type.text
        job_id, event, result, state = asyncio.run(_mes_single_job(opcua, admin, tmp_path, "forging-station-billet"))
        scan_id = result.ResultId.Id
        assert value(event, "JobId").Id == job_id and value(event, "ResultId").Id == scan_id
        assert (result.ResultState, result.PartId.Id, result.MeasId.Id) == (1, "forging-8", "shift-4")  # Completed
        assert state == ("Operational", "Ready")
        job = client.get(f"/v1/jobs/{job_id}").json()
        assert job["status"] == "succeeded", job
        worker_pids = {child.pid for child in psutil.Process(restarted.pid).children(recursive=True)}
        assert int(job["worker"].rsplit(":", 1)[1]) in worker_pids, (job, worker_pids)  # a worker, not the API
        inspected = client.get(f"/v1/scans/{scan_id}").json()
        assert (inspected["job_id"], inspected["part_id"]) == (job_id, "forging-8")
        assert inspected["part_type_id"] == part_type.json()["part_type_id"]
        assert client.get(inspected["links"]["report.json"]).json()["verdict"] == inspected["verdict"] == "OK"
        assert [v.Value for v in value(event, "ResultContent")][0] == result.ResultContent[0].Value == "OK"

    # Every port is on loopback unless configured otherwise; no secret in any log of the full scans.
    for name, process in e2e.processes.running:
        assert e2e.listening_addresses(process) <= {"127.0.0.1"}, (name, e2e.listening_addresses(process))
    e2e.assert_no_secrets_in_logs()
    errors = e2e.field_errors(tmp_path / "field.ply")
    assert errors["median_distance_mm"] < 0.5, errors
    assert errors["median_temperature_error_k"] < 1.0, errors
    assert errors["temperature_coverage"] > 0.8 and errors["p99_temperature_error_k"] < 1.0, errors
    assert events.states(f"{env['THERMOFIELD_SITE']}/station1/scans/{jobs[1]['scan_id']}")[-1]["status"] == "succeeded"


def _assert_in_order(states: list[dict]) -> None:
    """A job's MQTT states arrive in the order they happened: queued first, succeeded last, attempts never
    going back and, within an attempt, the fraction never going back."""
    assert states and states[0]["status"] == "queued" and states[-1]["status"] == "succeeded", states
    for before, after in zip(states, states[1:]):
        assert after["attempts"] >= before["attempts"], (before, after)
        if after["attempts"] == before["attempts"] and after["status"] == before["status"] == "running":
            assert after["fraction"] >= before["fraction"], (before, after)


class _ResultReadyListener:
    """An MES (asyncua, signed and encrypted), on a thread of its own, collecting the ResultReady events."""

    def __init__(self, endpoint: str, api_key: str, directory) -> None:
        self.endpoint, self.api_key, self.directory, self.received = endpoint, api_key, directory, []
        self._subscribed, self._stop = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._listen()), daemon=True)
        self._thread.start()
        assert self._subscribed.wait(60), f"no OPC UA server at {endpoint}"

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10)

    def wait_for(self, count: int, timeout_s: float = 30) -> bool:
        deadline = time.monotonic() + timeout_s
        while len(self.received) < count and time.monotonic() < deadline:
            time.sleep(0.1)
        return len(self.received) >= count

    async def _listen(self) -> None:
        certificate = await client_certificate(self.directory / "mes", self.directory / "opcua" / "trusted")
        async with Mes(self.endpoint, self.api_key, certificate) as mes:
            await mes.subscribe("ResultReadyEventType")
            self._subscribed.set()
            while not self._stop.is_set():
                self.received = [{"ResultId": value(event, "ResultId").Id, "PartId": value(event, "PartId").Id,
                                  "ResultState": value(event, "ResultState")}
                                 for event in mes.of_type("ResultReadyEventType")]
                await asyncio.sleep(0.1)


async def _mes_single_job(endpoint: str, api_key: str, directory, recipe: str):
    """An MES's single job: PrepareRecipe, StartSingleJob, its ResultReady and GetResultById; the job's id, the
    event, the result and the state the VisionSystem is left in."""
    certificate = await client_certificate(directory / "mes", directory / "opcua" / "trusted")
    # a generous request timeout: on a loaded machine a reply from the API can take longer than asyncua's 4 s
    async with Mes(endpoint, api_key, certificate, timeout_s=60) as mes:
        await mes.subscribe("ResultReadyEventType")
        internal, _, error = await mes.call("PrepareRecipe", ua.RecipeIdExternalDataType(Id=recipe), None)
        assert error == 0 and await mes.state() == ("Operational", "Ready"), internal
        job, error = await mes.call("StartSingleJob", ua.MeasIdDataType(Id="shift-4"),
                                    ua.PartIdDataType(Id="forging-8"), ua.RecipeIdExternalDataType(Id=recipe), None,
                                    ua.Variant([], ua.VariantType.Variant))
        assert error == 0
        assert await mes.wait_for(lambda: mes.of_type("ResultReadyEventType"), timeout_s=300), mes.events
        (event,) = mes.of_type("ResultReadyEventType")
        _, result, error = await mes.call("GetResultById", value(event, "ResultId"), ua.Variant(0, ua.VariantType.Int32))
        assert error == 0
        return job.Id, event, result, await mes.state()


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


def test_the_scaled_out_api_refuses_opc_ua_without_mqtt(deployment, tmp_path):
    import os
    import sys

    env = os.environ | deployment | {"THERMOFIELD_OPCUA_ENDPOINT": "opc.tcp://127.0.0.1:4840/thermofield",
                                     "THERMOFIELD_MQTT_HOST": ""}
    result = subprocess.run([sys.executable, "-m", "services.cli.main", "api"], env=env, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert "THERMOFIELD_MQTT_HOST" in result.stderr and "Traceback" not in result.stderr
