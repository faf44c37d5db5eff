"""The compose stack really running: docker/compose.yaml with docker/compose.local.yaml in podman.

Run by `make test-containers` (marker ``containers``; the default run leaves it out), which builds the images
first (docker/local/build-images.sh). The services start in the order their ``depends_on`` conditions ask
for; podman before 4.6 cannot wait for a healthy container, so this test runs every healthcheck itself
(``podman healthcheck run``) until it passes, then starts the next group. Then, over HTTP as a plant would:
an API key, a calibration set, a scan whose field is checked against the simulator's ground truth, its
``.rrd``, and a second scan during which the worker container running it is killed: the other worker
finishes it, once. Then as an MES over OPC UA (asyncua, Basic256Sha256 Sign&Encrypt, its certificate trusted by
copying it into the API container's PKI volume as docs/deployment.md says): a part type's recipe prepared, a
scan started by StartSingleJob, its ResultReady and GetResultById, and the verdict HTTP gives for the same scan.
The gateway image carries Aravis: the GenICam driver grabs a frame from Aravis' fake camera inside it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import asyncio

import httpx
import pytest
from asyncua import ua

from services.formats.rig import rig_to_json
from services.simulation.hot_part import write_forging_part
from services.simulation.presets import forging_rig
from tests.opcua.mes import Mes, client_certificate, value

pytestmark = [pytest.mark.integration, pytest.mark.containers, pytest.mark.timeout(1800)]

ROOT = Path(__file__).resolve().parents[2]
DOCKER = ROOT / "docker"
PROJECT = "thermofield-test"
# Started group by group, as depends_on orders them.
GROUPS = (("postgres", "rabbitmq", "mosquitto", "rerun"), ("gateway",), ("api", "worker"))
HEALTHY_WITHIN_S = 420.0


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Stack:
    """The compose project: podman-compose for the services, podman for the containers."""

    def __init__(self, log_dir: Path) -> None:
        self.api_port, self.rerun_port, self.mqtt_port = _free_port(), _free_port(), _free_port()
        self.opcua_port = _free_port()
        self.log_dir = log_dir
        self.env = os.environ | {
            "CONTAINERS_CONF": str(DOCKER / "local" / "containers.conf"),
            "THERMOFIELD_API_PUBLISH": f"127.0.0.1:{self.api_port}",
            "THERMOFIELD_RERUN_PUBLISH": f"127.0.0.1:{self.rerun_port}",
            "THERMOFIELD_MQTT_PUBLISH": f"127.0.0.1:{self.mqtt_port}",
            "THERMOFIELD_OPCUA_PUBLISH": f"127.0.0.1:{self.opcua_port}",
        }
        self.compose_command = [_podman_compose(), "-p", PROJECT, "-f", str(DOCKER / "compose.yaml"),
                                "-f", str(DOCKER / "compose.local.yaml")]

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    @property
    def opcua_url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.opcua_port}/thermofield"

    def compose(self, *arguments: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return subprocess.run([*self.compose_command, *arguments], env=self.env, capture_output=True, text=True,
                              timeout=timeout, cwd=DOCKER)

    def podman(self, *arguments: str, timeout: float = 120, check: bool = True) -> subprocess.CompletedProcess:
        result = subprocess.run(["podman", *arguments], env=self.env, capture_output=True, text=True,
                                timeout=timeout)
        if check and result.returncode != 0:
            raise AssertionError(f"podman {' '.join(arguments)} failed: {result.stderr[-2000:]}")
        return result

    def containers(self, service: str | None = None) -> list[dict]:
        """The project's containers (all states), optionally those of one service."""
        filters = ["--filter", f"label=io.podman.compose.project={PROJECT}"]
        if service:
            filters += ["--filter", f"label=com.docker.compose.service={service}"]
        listed = json.loads(self.podman("ps", "--all", "--format", "json", *filters).stdout or "[]")
        return sorted(listed, key=lambda container: container["Names"][0])

    def start(self, services: tuple[str, ...]) -> None:
        result = self.compose("up", "-d", "--no-deps", *services)
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]

    def wait_until_healthy(self, services: tuple[str, ...]) -> dict[str, float]:
        """Run each container's healthcheck until it passes; the seconds each took from now."""
        started, waiting, took = time.monotonic(), {}, {}
        for service in services:
            names = [container["Names"][0] for container in self.containers(service)]
            assert names, f"compose started no {service} container"
            waiting.update({name: service for name in names})
        while waiting:
            for name in list(waiting):
                state = self.podman("inspect", "--format", "{{.State.Status}}", name).stdout.strip()
                if state in ("exited", "stopped") and not self._restarting(name):
                    raise AssertionError(f"{name} exited:\n{self.logs(name)}")
                if self._healthy(name):
                    took[name] = time.monotonic() - started
                    del waiting[name]
            if waiting and time.monotonic() - started > HEALTHY_WITHIN_S:
                logs = "\n".join(f"--- {name}\n{self.logs(name)}" for name in waiting)
                raise AssertionError(f"not healthy within {HEALTHY_WITHIN_S:.0f} s: {sorted(waiting)}\n{logs}")
            time.sleep(2)
        return took

    def _healthy(self, name: str) -> bool:
        try:
            return self.podman("healthcheck", "run", name, check=False, timeout=60).returncode == 0
        except subprocess.TimeoutExpired:
            return False  # a loaded machine: try again

    def _restarting(self, name: str) -> bool:
        return self.podman("inspect", "--format", "{{.State.Restarting}}", name, check=False).stdout.strip() == "true"

    def logs(self, name: str, lines: int = 60) -> str:
        result = self.podman("logs", "--tail", str(lines), name, check=False)
        return (result.stdout + result.stderr)[-6000:]

    def down(self) -> None:
        self.compose("down", "--volumes", "--timeout", "5", timeout=300)
        # podman-compose leaves the project's network behind when a container refused to stop in time.
        for container in self.containers():
            self.podman("rm", "--force", "--volumes", "--time", "0", container["Id"], check=False)
        for volume in self.podman("volume", "ls", "--quiet", "--filter",
                                  f"label=io.podman.compose.project={PROJECT}").stdout.split():
            self.podman("volume", "rm", "--force", volume, check=False)


def _podman_compose() -> str:
    found = shutil.which("podman-compose", path=str(Path(sys.executable).parent)) or shutil.which("podman-compose")
    assert found, "podman-compose is not installed: run `make test-containers`, which installs it"
    return found


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    assert shutil.which("podman"), "podman is not installed: run `make test-containers`, which installs it"
    stack = Stack(tmp_path_factory.mktemp("stack"))
    stack.down()  # what an interrupted run may have left
    timings = {}
    try:
        for group in GROUPS:
            stack.start(group)
            timings.update(stack.wait_until_healthy(group))
        print(f"\nhealthy after (s, from its group's start): "
              f"{json.dumps({name: round(s, 1) for name, s in timings.items()})}", flush=True)
        yield stack
    finally:
        stack.down()


def _create_key(stack: Stack) -> str:
    api = stack.containers("api")[0]["Names"][0]
    result = stack.podman("exec", api, "thermofield", "apikey", "create", "--scopes", "admin", "--name", "test")
    return result.stdout.strip()


def _wait_for(client: httpx.Client, job_id: str, reached, timeout_s: float = 180.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = client.get(f"/v1/jobs/{job_id}").json()
        if reached(state):
            return state
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not reach the state within {timeout_s} s: {state}")


def test_the_stack_scans_over_http_and_opc_ua_and_survives_a_killed_worker(stack, tmp_path):
    from tests.integration.conftest import field_errors, follow_events

    services = {container["Labels"]["com.docker.compose.service"] for container in stack.containers()}
    assert services == {"api", "worker", "gateway", "rerun", "postgres", "rabbitmq", "mosquitto"}
    workers = stack.containers("worker")
    assert len(workers) == 2
    for container in stack.containers():
        user = stack.podman("exec", container["Id"], "id", "-u").stdout.strip()
        assert user != "0", f"{container['Names'][0]} runs as root"

    key = _create_key(stack)
    with httpx.Client(base_url=stack.api_url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "true rig", "activate": "true"})
        assert created.status_code == 201, created.text

        first = client.post("/v1/scans", json={"part_id": "container-1"}).json()
        final = follow_events(client, first["job_id"])[-1]
        assert final[0] == "done" and final[1]["status"] == "succeeded", final
        scan = client.get(f"/v1/scans/{first['scan_id']}").json()
        (tmp_path / "field.ply").write_bytes(client.get(scan["links"]["field.ply"]).content)
        recording = client.get(scan["links"]["field.rrd"])
        assert recording.status_code == 200 and recording.content[:4] == b"RRF2"

        # The second scan: its worker container is killed while it runs; RabbitMQ redelivers the message,
        # unacknowledged, to the other worker, which runs the job as its second attempt.
        second = client.post("/v1/scans", headers={"Idempotency-Key": "kill-a-worker"},
                             json={"part_id": "container-2"}).json()
        running = _wait_for(client, second["job_id"], lambda state: state["status"] == "running")
        host = running["worker"].split(":")[0]
        victim = next(container for container in workers if container["Id"].startswith(host))
        stack.podman("kill", "--signal", "KILL", victim["Id"])
        final = follow_events(client, second["job_id"])[-1][1]
        assert final["status"] == "succeeded" and final["attempts"] == 2, final
        assert not final["worker"].startswith(host), final
        # Once: one job for the scan, one scan for the key, and a retry of the request creates nothing.
        assert client.post("/v1/scans", headers={"Idempotency-Key": "kill-a-worker"},
                           json={"part_id": "container-2"}).json() == second
        jobs = [job for job in client.get("/v1/jobs").json() if job["scan_id"] == second["scan_id"]]
        assert [(job["job_id"], job["status"]) for job in jobs] == [(second["job_id"], "succeeded")]
        assert [s["scan_id"] for s in client.get("/v1/scans").json()].count(second["scan_id"]) == 1

        # An MES over OPC UA: a part type uploaded over HTTP is its recipe, prepared and started by StartSingleJob;
        # a worker container inspects the scan; ResultReady and GetResultById give the verdict HTTP gives.
        part_file = write_forging_part(tmp_path / "part")
        part_type = client.post("/v1/part-types", files={
            "part": ("part.json", part_file.read_bytes()),
            "mesh": ("forging.stl", (part_file.parent / "forging.stl").read_bytes())})
        assert part_type.status_code == 201, part_type.text
        certificate = asyncio.run(client_certificate(tmp_path / "mes", None))
        _trust(stack, certificate[0])
        job_id, event, result, state = asyncio.run(_mes_single_job(stack.opcua_url, key, certificate,
                                                                   "forging-station-billet"))
        scan_id = result.ResultId.Id
        assert value(event, "JobId").Id == job_id and value(event, "ResultId").Id == scan_id
        assert (result.ResultState, result.PartId.Id, result.MeasId.Id) == (1, "container-3", "shift-5")  # Completed
        assert state == ("Operational", "Ready")
        job = client.get(f"/v1/jobs/{job_id}").json()
        assert job["status"] == "succeeded", job
        assert any(container["Id"].startswith(job["worker"].split(":")[0]) for container in workers), job
        inspected = client.get(f"/v1/scans/{scan_id}").json()
        assert (inspected["job_id"], inspected["part_id"]) == (job_id, "container-3")
        assert inspected["part_type_id"] == part_type.json()["part_type_id"]
        assert client.get(inspected["links"]["report.json"]).json()["verdict"] == inspected["verdict"] == "OK"
        assert [v.Value for v in value(event, "ResultContent")][0] == result.ResultContent[0].Value == "OK"

        # A new API container (an image update recreates it) keeps the server's certificate and the trusted MES:
        # they are on the PKI volume, under the container's fixed host name.
        issued = _server_certificate(stack)
        stack.podman("rm", "--force", "--time", "10", stack.containers("api")[0]["Id"])
        stack.start(("api",))
        stack.wait_until_healthy(("api",))
        assert _server_certificate(stack) == issued
        assert asyncio.run(_mes_result(stack.opcua_url, key, certificate, scan_id)) == (1, "OK")

    errors = field_errors(tmp_path / "field.ply")
    print(f"\nfield through the containers: {json.dumps({k: round(v, 4) for k, v in errors.items()})}")
    assert errors["points"] > 100_000, errors
    assert errors["median_distance_mm"] < 0.5, errors
    assert errors["median_temperature_error_k"] < 1.0, errors
    # docs/temperature-field.md: 85.2 % of the seen points get a temperature, the 99th percentile error 0.31 K
    assert errors["temperature_coverage"] > 0.8, errors
    assert errors["p99_temperature_error_k"] < 1.0, errors


def _trust(stack: Stack, certificate: Path) -> None:
    """Trust an MES's certificate as docs/deployment.md says: copied into the trusted/ directory of the API
    container's PKI volume (read by the server at each connection; no restart)."""
    api = stack.containers("api")[0]["Names"][0]
    certificate.chmod(0o644)  # the copy keeps the mode (and root as owner): readable by the server's user
    stack.podman("cp", str(certificate), f"{api}:/data/opcua/trusted/{certificate.name}")


async def _mes_single_job(endpoint: str, api_key: str, certificate: tuple[Path, Path], recipe: str):
    """PrepareRecipe, StartSingleJob, its ResultReady and GetResultById: the job's id, the event, the result and the
    state the VisionSystem is left in."""
    # generous timeouts: the API container answers slowly on a loaded machine
    async with Mes(endpoint, api_key, certificate, timeout_s=60, watchdog_s=30) as mes:
        await mes.subscribe("ResultReadyEventType")
        internal, _, error = await mes.call("PrepareRecipe", ua.RecipeIdExternalDataType(Id=recipe), None)
        assert error == 0 and await mes.state() == ("Operational", "Ready"), internal
        job, error = await mes.call("StartSingleJob", ua.MeasIdDataType(Id="shift-5"),
                                    ua.PartIdDataType(Id="container-3"), ua.RecipeIdExternalDataType(Id=recipe), None,
                                    ua.Variant([], ua.VariantType.Variant))
        assert error == 0
        assert await mes.wait_for(lambda: mes.of_type("ResultReadyEventType"), timeout_s=600), mes.events
        (event,) = mes.of_type("ResultReadyEventType")
        _, result, error = await mes.call("GetResultById", value(event, "ResultId"), ua.Variant(0, ua.VariantType.Int32))
        assert error == 0
        return job.Id, event, result, await mes.state()


def _server_certificate(stack: Stack) -> str:
    """The SHA-256 of the API container's OPC UA server certificate."""
    api = stack.containers("api")[0]["Names"][0]
    return stack.podman("exec", api, "sha256sum", "/data/opcua/server-certificate.der").stdout.split()[0]


async def _mes_result(endpoint: str, api_key: str, certificate: tuple[Path, Path], scan_id: str) -> tuple[int, str]:
    """A scan's result state and verdict by GetResultById."""
    async with Mes(endpoint, api_key, certificate, timeout_s=60, watchdog_s=30) as mes:
        _, result, error = await mes.call("GetResultById", ua.ResultIdDataType(Id=scan_id),
                                          ua.Variant(0, ua.VariantType.Int32))
        assert error == 0
        return result.ResultState, result.ResultContent[0].Value


def test_the_gateway_image_carries_aravis():
    """Aravis 0.8 in the gateway image: arv-tool-0.8 runs, and thermofield's GenICam driver opens Aravis'
    in-process fake camera and grabs a Mono16 frame at its full depth (no network: nothing is discovered)."""
    image = f"localhost/thermofield-gateway:{_version()}"
    env = os.environ | {"CONTAINERS_CONF": str(DOCKER / "local" / "containers.conf")}
    tool = subprocess.run(["podman", "run", "--rm", "--network", "none", "--entrypoint", "arv-tool-0.8", image,
                           "--help"], env=env, capture_output=True, text=True, timeout=300)
    assert tool.returncode == 0 and "arv-tool" in tool.stdout + tool.stderr, tool.stderr[-2000:]
    grab = ("import json\n"
            "from device_gateway.drivers.genicam import GenicamCamera\n"
            "camera = GenicamCamera(device_id='Fake_1', pixel_format='Mono16', trigger='Software')\n"
            "camera.open()\n"
            "frame = camera.grab(timeout_s=10.0)\n"
            "print(json.dumps({'model': camera.info.model, 'dtype': str(frame.image.dtype),\n"
            "                  'shape': frame.image.shape, 'max': int(frame.image.max())}))\n"
            "camera.close()\n")
    result = subprocess.run(["podman", "run", "--rm", "--network", "none", "--entrypoint", "python", image, "-c",
                             grab], env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    frame = json.loads(result.stdout.strip().splitlines()[-1])
    assert (frame["model"], frame["dtype"]) == ("Aravis Fake", "uint16"), frame
    assert len(frame["shape"]) == 2 and frame["max"] > 255, frame  # 16 bits, not cut to 8


def _version() -> str:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
