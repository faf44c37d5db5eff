"""Helpers for the end-to-end tests: real processes (the same commands the compose file runs),
real PostgreSQL, RabbitMQ and Mosquitto, and the simulator's ground truth to check the field."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import httpx
import numpy as np
import paho.mqtt.client as mqtt
import pytest
from sqlalchemy import text

from services.db.engine import make_engine
from services.formats.ply import read_cloud
from services.geometry.camera import pixel_rays, project_points
from services.jobs.queue import delete_job_queues
from services.simulation.presets import forging_rig, forging_scene
from services.simulation.raycast import cast_rays
from services.simulation.thermal import forging_temperatures, seen_by, surface_temperature

THERMOFIELD = [sys.executable, "-m", "services.cli.main"]
# The local PostgreSQL trusts 127.0.0.1 and ignores the password: it is there so that a log that leaks the
# database URL's password shows it (each session's is new, so it cannot appear by chance).
POSTGRES_PASSWORD = f"tf-pg-{uuid.uuid4().hex}"
POSTGRES_URL = f"postgresql+psycopg://postgres:{POSTGRES_PASSWORD}@127.0.0.1:5432/test"
BROKER_USER, BROKER_PASSWORD = "guest", "guest"
BROKER_URL = f"amqp://{BROKER_USER}:{BROKER_PASSWORD}@127.0.0.1:5672"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Processes:
    """Started child processes, stopped (SIGTERM, then SIGKILL) at the end of the test."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.running: list[tuple[str, subprocess.Popen]] = []

    def start(self, name: str, arguments: list[str], env: dict[str, str]) -> subprocess.Popen:
        log = open(self.log_dir / f"{name}.log", "wb")
        process = subprocess.Popen(THERMOFIELD + arguments, env=os.environ | env, stdout=log, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=True)
        self.running.append((name, process))
        return process

    def log(self, name: str) -> str:
        return (self.log_dir / f"{name}.log").read_text(errors="replace")

    def stop(self, process: subprocess.Popen, sig: int = signal.SIGTERM) -> None:
        if process.poll() is None:
            os.killpg(process.pid, sig)
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()

    def assert_no_secrets_in_logs(self, secrets: dict[str, str]) -> None:
        """No log of any started process contains a secret (``secrets``: what each is, its text)."""
        assert self.running, "no process was started: no log to search"
        for name, _ in self.running:
            log = self.log(name)
            for what, secret in secrets.items():
                assert secret not in log, f"{name}'s log contains {what}"

    def stop_all(self) -> None:
        for _, process in reversed(self.running):
            self.stop(process)


    def wait_until_healthy(self, url: str, name: str, timeout_s: float = 180.0) -> None:
        process = dict(self.running)[name]
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if process.poll() is not None:
                raise AssertionError(f"{name} exited with {process.returncode}:\n{self.log(name)[-3000:]}")
            try:
                if httpx.get(url, timeout=2.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.25)
        raise AssertionError(f"{name} did not become healthy at {url}:\n{self.log(name)[-3000:]}")


def create_key(env: dict[str, str], scopes: list[str]) -> str:
    result = subprocess.run(THERMOFIELD + ["apikey", "create", "--scopes", *scopes], env=os.environ | env,
                            capture_output=True, text=True, timeout=120, check=True)
    return result.stdout.strip()


class MqttRecorder:
    """Subscribes to a topic prefix and keeps every message; clears retained ones at the end."""

    def __init__(self, prefix: str) -> None:
        self.messages: list[tuple[str, dict, bool]] = []
        self._lock = threading.Lock()
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        self._client.on_message = self._on_message
        self._client.connect("127.0.0.1", 1883)
        self._client.subscribe(f"{prefix}/#", qos=1)
        self._client.loop_start()

    def _on_message(self, client, userdata, message) -> None:
        if message.payload:
            with self._lock:
                self.messages.append((message.topic, json.loads(message.payload), bool(message.retain)))

    def states(self, topic: str) -> list[dict]:
        with self._lock:
            return [state for name, state, _ in self.messages if name == topic]

    def close(self) -> None:
        with self._lock:
            topics = {name for name, _, _ in self.messages}
        for topic in topics:
            self._client.publish(topic, b"", qos=1, retain=True).wait_for_publish(5)
        self._client.loop_stop()
        self._client.disconnect()




def follow_events(client: httpx.Client, job_id: str, timeout_s: float = 300.0) -> list[tuple[str, dict]]:
    """Read the job's server-sent events until ``done``; returns (event, state) pairs."""
    events, name = [], None
    with client.stream("GET", f"/v1/jobs/{job_id}/events", timeout=timeout_s) as response:
        assert response.status_code == 200 and response.headers["content-type"].startswith("text/event-stream")
        for line in response.iter_lines():
            if line.startswith("event:"):
                name = line.split(":", 1)[1].strip()
            elif line.startswith("data:"):
                events.append((name, json.loads(line.split(":", 1)[1])))
                if name == "done":
                    break
    return events


def field_errors(path: Path) -> dict[str, float]:
    """Geometry and temperature errors of a field.ply against the simulated station's ground truth.

    Each point's camera pixel (u, v) is traced through the true rig into the true scene:
    the geometric error is the distance from the point to that true surface point, the
    temperature error the difference from the true surface temperature there, over the
    points that got a temperature and whose true point the thermal camera sees. The coverage is the
    share of those seen points that got a temperature: about 85 % on this scene, the mixed-pixel test
    leaving a band about 4 thermal pixels wide along its depth edges without one
    (docs/temperature-field.md).
    """
    field = read_cloud(path)
    rig, scene = forging_rig(), forging_scene()
    camera, thermal = rig.devices["camera"], rig.devices["thermal"]
    pixels = np.column_stack([field["u"], field["v"]]).astype(np.float64)
    origin, directions = pixel_rays(pixels, camera.K, camera.dist, camera.R, camera.t)
    hits = cast_rays(scene, origin, directions)
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    on_surface = hits.surface >= 0
    distance = np.linalg.norm(points[on_surface] - hits.points[on_surface], axis=1)
    temperature = np.asarray(field["temperature"], dtype=np.float64)
    truth = surface_temperature(forging_temperatures(), hits.points[on_surface], hits.surface[on_surface])
    measured = temperature[on_surface]
    in_frame = project_points(hits.points[on_surface], thermal.K, thermal.dist, thermal.R,
                              thermal.t)
    inside = ((in_frame >= 0) & (in_frame <= [thermal.width - 1, thermal.height - 1])).all(axis=1)
    visible = seen_by(scene, thermal, hits.points[on_surface]) & inside
    compared = np.isfinite(measured) & visible
    hidden = ~visible
    return {
        "points": float(len(points)),
        "median_distance_mm": float(np.median(distance)),
        "median_temperature_error_k": float(np.median(np.abs(measured[compared] - truth[compared]))),
        "p99_temperature_error_k": float(np.percentile(np.abs(measured[compared] - truth[compared]), 99)),
        "temperature_coverage": float(compared.sum() / max(visible.sum(), 1)),
        "hidden_points_nan": float(np.mean(~np.isfinite(measured[hidden]))) if hidden.any() else 1.0,
    }


def listening_addresses(process: subprocess.Popen) -> set[str]:
    """The addresses the process and its children listen on (TCP)."""
    import psutil

    if process.poll() is not None:
        return set()  # stopped by the test
    root = psutil.Process(process.pid)
    addresses = set()
    for member in [root, *root.children(recursive=True)]:
        try:
            connections = member.net_connections(kind="tcp")
        except psutil.NoSuchProcess:
            continue
        addresses.update(c.laddr.ip for c in connections if c.status == psutil.CONN_LISTEN)
    return addresses


class EndToEnd:
    """What an end-to-end test uses: processes, ports, keys, MQTT, SSE and ground truth."""

    free_port = staticmethod(free_port)
    follow_events = staticmethod(follow_events)
    field_errors = staticmethod(field_errors)
    listening_addresses = staticmethod(listening_addresses)

    def __init__(self, directory: Path) -> None:
        self.processes = Processes(directory)
        self.recorders: list[MqttRecorder] = []
        self.api_keys: list[str] = []

    def create_key(self, env: dict[str, str], scopes: list[str]) -> str:
        """A new API key's secret, remembered for :meth:`assert_no_secrets_in_logs`."""
        self.api_keys.append(create_key(env, scopes))
        return self.api_keys[-1]

    def assert_no_secrets_in_logs(self) -> None:
        """No log of the started processes holds the database's or the broker's password or any API key
        created."""
        secrets = {"the PostgreSQL password": POSTGRES_PASSWORD,
                   # alone, in any form (a URL, a repr of credentials); the user's name is the same word, and no
                   # log names it either
                   "the broker's password": BROKER_PASSWORD,
                   **{f"API key {number + 1} of {len(self.api_keys)}": key for number, key in enumerate(self.api_keys)}}
        self.processes.assert_no_secrets_in_logs(secrets)

    def mqtt(self, prefix: str) -> MqttRecorder:
        self.recorders.append(MqttRecorder(prefix))
        return self.recorders[-1]

    def close(self) -> None:
        self.processes.stop_all()
        for recorder in self.recorders:
            recorder.close()


@pytest.fixture
def e2e(tmp_path):
    harness = EndToEnd(tmp_path)
    yield harness
    harness.close()


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
    delete_job_queues(BROKER_URL, env["THERMOFIELD_JOB_QUEUE"])
