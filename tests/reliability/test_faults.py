"""Faults against real servers of the test's own: PostgreSQL stopped and restarted under the API, Mosquitto
stopped while jobs change state, RabbitMQ stopped or killed while scans are requested (the outbox), the
artifact store's disk full under uploads."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
import uuid

import httpx
import paho.mqtt.client as mqtt
import pytest
from sqlalchemy import text

from services.db.apikeys import create_api_key
from services.db.engine import make_engine, make_sessions, migrate
from services.db.models import IdempotencyRecord, Job
from services.events.mqtt import EventPublisher, job_topic, scan_topic, station_topic
from services.formats.rig import rig_to_json
from services.jobs.tracker import JobTracker
from services.settings import Settings
from services.simulation.presets import forging_rig
from services.storage.artifacts import ArtifactStore
from services.jobs.queue import JobQueue, job_broker
from services.runtime import Runtime
from tests.reliability.conftest import free_port

pytestmark = pytest.mark.integration

PROBLEM = "application/problem+json"
POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


def _client(runtime):
    from fastapi.testclient import TestClient

    from api.app import create_app

    return TestClient(create_app(runtime, JobQueue(job_broker(runtime.settings), runtime.settings.job_queue)),
                      raise_server_exceptions=False)


def _runtime(url: str, tmp_path, schema: str | None = None, **settings) -> Runtime:
    engine = make_engine(url, schema)
    migrate(engine)
    sessions = make_sessions(engine)
    config = Settings(data_dir=tmp_path, **{"broker_url": "", "mqtt_host": "", **settings})
    return Runtime(config, engine, sessions, ArtifactStore(config.resolved_artifact_dir), JobTracker(sessions))


def _key(runtime, scope="admin") -> dict[str, str]:
    with runtime.sessions.begin() as session:
        return {"Authorization": f"Bearer {create_api_key(session, scope, [scope])[1]}"}


def test_postgres_stopped_and_restarted(private_postgres, tmp_path):
    runtime = _runtime(private_postgres.url, tmp_path, min_free_bytes=0)
    headers = _key(runtime)
    with _client(runtime) as client:
        assert client.get("/readyz").status_code == 200
        assert client.get("/v1/jobs", headers=headers).status_code == 200
        private_postgres.stop()
        try:
            ready = client.get("/readyz")
            assert ready.status_code == 503 and ready.headers["content-type"] == PROBLEM
            assert int(ready.headers["retry-after"]) > 0 and "database" in ready.json()["detail"]
            for method, path in (("GET", "/v1/jobs"), ("GET", "/v1/jobs/any"), ("GET", "/v1/scans"),
                                 ("POST", "/v1/scans"), ("GET", "/v1/calibration-sets")):
                response = client.request(method, path, headers=headers)
                assert response.status_code == 503, (path, response.text)
                assert response.headers["content-type"] == PROBLEM and int(response.headers["retry-after"]) > 0
                assert response.json()["type"].endswith("/database-unavailable")
            assert client.get("/healthz").status_code == 200  # the process itself is alive
        finally:
            private_postgres.start()
        deadline = time.monotonic() + 30  # recovery needs no manual step: the pool reconnects
        while client.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert client.get("/readyz").status_code == 200
        created = client.post("/v1/calibration-sets", headers=headers,
                              files={"rig": ("rig.json", rig_to_json(forging_rig()), "application/json")},
                              data={"name": "after the outage", "activate": "true"})
        assert created.status_code == 201, created.text
        scan = client.post("/v1/scans", headers={**headers, "Idempotency-Key": "after"})
        assert scan.status_code == 202
        assert client.get(scan.headers["location"], headers=headers).json()["status"] == "queued"  # the poll's path
    with runtime.sessions() as session:
        assert session.query(Job).count() == 1 and session.query(IdempotencyRecord).count() == 1


class _Subscriber:
    """An MES-like subscriber: QoS 1 on the station's tree, reconnecting by itself, optionally with a persistent
    session (fixed client id, clean session off: the broker queues its messages while it is away and keeps its
    subscription across a restart); every message recorded as (topic, state, retained) in arrival order."""

    def __init__(self, port: int, prefix: str, client_id: str = "", persistent: bool = False) -> None:
        self.received: list[tuple[str, dict, bool]] = []
        self.subscribed = threading.Event()
        self.client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id,
                                  clean_session=not persistent)
        self.client.reconnect_delay_set(min_delay=1, max_delay=2)
        self.client.on_connect = lambda client, userdata, flags, *_: (
            None if flags.session_present else client.subscribe(f"{prefix}/#", qos=1))  # the broker kept it
        self.client.on_subscribe = lambda *_: self.subscribed.set()
        self.client.on_message = lambda c, u, message: self.received.append(
            (message.topic, json.loads(message.payload), bool(message.retain)))
        self.client.connect_async("127.0.0.1", port, keepalive=5)
        self.client.loop_start()
        assert self.subscribed.wait(30), "the subscriber never got its SUBACK"

    def states(self, topic: str) -> list[dict]:
        return [state for received_topic, state, _ in list(self.received) if received_topic == topic]

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()


def _once_each(states: list[dict]) -> list[tuple]:
    """(status, stage) of each state in arrival order, a repeat dropped: QoS 1 is at least once, so the broker
    delivers again a message whose acknowledgement it had not recorded when it stopped (JobStateSubscriber
    drops those repeats the same way)."""
    seen: list[tuple] = []
    for state in states:
        key = (state["status"], state["stage"], state["fraction"], state["attempts"])
        if key not in seen:
            seen.append(key)
    return [key[:2] for key in seen]


_MARKER = {"marker": True}  # published after the states: once heard, every state before it on its topic was


def _wait_for(condition, timeout_s: float = 30.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


def test_mosquitto_stopped_jobs_go_on_and_states_arrive_when_it_returns(private_mosquitto, tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
    migrate(engine)
    prefix = "fault/station1"
    publisher = EventPublisher("127.0.0.1", private_mosquitto.port, prefix)
    mes = _Subscriber(private_mosquitto.port, prefix, client_id=f"mes-{uuid.uuid4().hex[:8]}", persistent=True)
    tracker = JobTracker(make_sessions(engine), publisher)
    try:
        with tracker.sessions.begin() as session:
            job = tracker.create(session, "scan", {"scan_id": "s1"})
        tracker.announce(job)
        tracker.start(job.id)
        job_id = job.id
        assert _wait_for(lambda: len(mes.states(station_topic(prefix))) == 2), mes.received
        before_the_stop = len(mes.received)
        private_mosquitto.stop()
        stages = ["capture", "reconstruct", "fuse", "store"]
        for index, stage in enumerate(stages):  # the job goes on while the broker is down
            tracker.progress(job_id, stage, index / len(stages))
        tracker.succeed(job_id, {"artifacts": {}})
        with tracker.sessions() as session:
            assert session.get(Job, job_id).status == "succeeded"  # the database is the source of truth
        assert not mes.client.is_connected() and not publisher._client.is_connected()
        time.sleep(1.0)  # the test: the broker stays down a while, both clients retrying
        assert len(mes.received) == before_the_stop  # nothing arrived while it was down
    finally:
        private_mosquitto.start()
    try:
        # the publisher re-sends what it queued, the broker queues it in the MES's persistent session
        assert _wait_for(lambda: any(state["status"] == "succeeded"
                                     for state in mes.states(job_topic(prefix, job_id)))), mes.received
        # Any duplicate (QoS 1 is at least once) comes before a marker published after it on its topic: MQTT
        # keeps the order of one topic's messages.
        topics = (job_topic(prefix, job_id), scan_topic(prefix, "s1"), station_topic(prefix))
        for topic in topics:
            publisher.publish(topic, _MARKER)
        assert _wait_for(lambda: all(_MARKER in mes.states(topic) for topic in topics)), mes.received
        mes.received[:] = [message for message in mes.received if message[1] != _MARKER]
        late = _Subscriber(private_mosquitto.port, prefix)
        assert _wait_for(lambda: late.states(station_topic(prefix)))
    finally:
        publisher.close()
        mes.close()
    per_job = _once_each(mes.states(job_topic(prefix, job_id)))  # every state queued while it was down, in order
    assert per_job == [("queued", "queued"), ("running", "starting"), *[("running", stage) for stage in stages],
                       ("succeeded", "done")], [(topic, state["stage"]) for topic, state, _ in mes.received]
    per_scan = [stage for _, stage in _once_each(mes.states(scan_topic(prefix, "s1")))]
    assert per_scan == ["queued", "starting", *stages, "done"], per_scan
    assert not any(retained for topic, _, retained in mes.received if topic != station_topic(prefix))
    station = mes.states(station_topic(prefix))
    assert [stage for _, stage in _once_each(station)] == per_scan and station[-1]["status"] == "succeeded"
    repeats = len(mes.received) - 3 * len(per_scan)
    assert 0 <= repeats <= before_the_stop, mes.received  # at most the states delivered before the stop came again
    retained = [(state, retain) for topic, state, retain in late.received if topic == station_topic(prefix)]
    late.close()
    assert len(retained) == 1 and retained[0][1], late.received  # a late subscriber gets the station's state,
    assert retained[0][0]["status"] == "succeeded" and retained[0][0]["job_id"] == job_id  # retained: the last one


@pytest.mark.reliability  # a few minutes: the embedded service's start and a whole scan (make test-reliability)
def test_a_real_scan_with_mosquitto_down_publishes_its_states_when_it_returns(private_mosquitto, tmp_path):
    """`thermofield serve` scans the simulated part while its broker is down; an MES subscribed before gets the
    scan job's every state, in order, when the broker returns, and the station's retained state is the last."""
    site = f"fault-{uuid.uuid4().hex[:8]}"
    env = os.environ | {"THERMOFIELD_DATA_DIR": str(tmp_path / "data"), "THERMOFIELD_SITE": site,
                        "THERMOFIELD_MQTT_PORT": str(private_mosquitto.port)}
    command = [sys.executable, "-m", "services.cli.main"]
    port = free_port()
    with open(tmp_path / "serve.log", "wb") as log:
        serve = subprocess.Popen([*command, "serve", "--port", str(port), "--gateway-port", str(free_port()),
                                  "--rerun-port", str(free_port()), "--rerun-web-port", str(free_port())], env=env,
                                 stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, start_new_session=True)
    prefix = f"{site}/station1"
    mes = _Subscriber(private_mosquitto.port, prefix, client_id=f"mes-{uuid.uuid4().hex[:8]}", persistent=True)
    try:
        assert _wait_for(lambda: serve.poll() is not None or _ready(f"http://127.0.0.1:{port}/readyz"), 300), \
            (tmp_path / "serve.log").read_text()[-3000:]
        key = subprocess.run([*command, "apikey", "create", "--scopes", "operate"], env=env, capture_output=True,
                             text=True, timeout=120, check=True).stdout.strip()
        with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {key}"},
                          timeout=30) as client:
            before_the_stop = len(mes.received)
            private_mosquitto.stop()
            try:
                accepted = client.post("/v1/scans", json={"part_id": "billet-mqtt"})
                assert accepted.status_code == 202, accepted.text
                job_id, scan_id = accepted.json()["job_id"], accepted.json()["scan_id"]
                assert _wait_for(lambda: client.get(f"/v1/jobs/{job_id}").json()["status"] in ("succeeded", "failed"),
                                 300)
                assert client.get(f"/v1/jobs/{job_id}").json()["status"] == "succeeded"  # the scan went on
                assert len(mes.received) == before_the_stop  # nothing arrived while the broker was down
            finally:
                private_mosquitto.start()
        assert _wait_for(lambda: any(state["status"] == "succeeded" for state in mes.states(job_topic(prefix, job_id))),
                         60), mes.received
        time.sleep(1.0)  # the test's window: any repeat would have come by now (the service's own publisher)
        late = _Subscriber(private_mosquitto.port, prefix)
        assert _wait_for(lambda: late.states(station_topic(prefix)))
        retained = [(state, retain) for topic, state, retain in late.received if topic == station_topic(prefix)]
        late.close()
    finally:
        mes.close()
        if serve.poll() is None:
            os.killpg(serve.pid, signal.SIGTERM)
            try:
                serve.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(serve.pid, signal.SIGKILL)
                serve.wait()
    states = [state for state in mes.states(job_topic(prefix, job_id))]
    per_job = _once_each(states)
    assert per_job[0] == ("queued", "queued") and per_job[-1] == ("succeeded", "done"), per_job
    statuses = [status for status, _ in per_job]
    assert statuses == sorted(statuses, key=["queued", "running", "succeeded"].index), per_job  # never back
    stages = [stage for _, stage in per_job]
    assert [stage for stage in ("capture", "reconstruct", "fuse", "store") if stage in stages] == \
        ["capture", "reconstruct", "fuse", "store"], per_job
    assert [stages.index(stage) for stage in ("capture", "reconstruct", "fuse", "store")] == \
        sorted(stages.index(stage) for stage in ("capture", "reconstruct", "fuse", "store")), per_job  # in order
    fractions = [state["fraction"] for state in states if state["status"] == "running"]
    assert fractions == sorted(fractions), fractions
    assert [stage for _, stage in _once_each(mes.states(scan_topic(prefix, scan_id)))] == stages
    assert len(retained) == 1 and retained[0][1], late.received
    assert retained[0][0]["status"] == "succeeded" and retained[0][0]["scan_id"] == scan_id


def _ready(url: str) -> bool:
    try:
        return httpx.get(url, timeout=2.0).status_code == 200
    except httpx.HTTPError:
        return False


def test_disk_full_while_storing_uploads(small_disk, tmp_path):
    disk = small_disk(2 << 20)
    runtime = _runtime(f"sqlite:///{tmp_path / 'service.db'}", tmp_path, artifact_dir=disk,
                       min_free_bytes=1 << 20, max_image_bytes=8 << 20)
    headers = _key(runtime)
    rig = rig_to_json(forging_rig())
    with _client(runtime) as client:
        assert client.get("/readyz").status_code == 200
        created = client.post("/v1/calibration-sets", headers=headers, files={"rig": ("rig.json", rig)},
                              data={"name": "rig", "activate": "true"})
        calibration_id = created.json()["calibration_set_id"]
        filler = disk / "filler"  # another tenant of the disk fills it up to a few kB
        free = runtime.store.free_bytes()
        with open(filler, "wb") as handle:
            handle.write(b"\0" * (free - 8192))
        import cv2
        import numpy as np

        camera = forging_rig().devices["camera"]
        noise = np.random.default_rng(0).integers(0, 255, (camera.height, camera.width), dtype=np.uint8)
        image = cv2.imencode(".png", noise)[1].tobytes()  # incompressible: larger than the space left
        thermal = forging_rig().devices["thermal"]
        device_image = cv2.imencode(".png", np.zeros((thermal.height, thermal.width), np.uint16))[1].tobytes()
        files = [("board", ("board.json", '{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 25}'))]
        files += [("reference_images", (f"c{i}.png", image)) for i in range(3)]
        files += [("device_images", (f"t{i}.png", device_image)) for i in range(3)]
        response = client.post(f"/v1/calibration-sets/{calibration_id}/stereo", headers=headers, files=files,
                               data={"name": "recalibrated"})
        assert response.status_code == 503, response.text
        assert response.headers["content-type"] == PROBLEM and response.json()["type"].endswith("/storage-full")
        assert int(response.headers["retry-after"]) > 0
        assert list((disk / "incoming").iterdir()) == []  # nothing half-written
        ready = client.get("/readyz")
        assert ready.status_code == 503 and "free" in ready.json()["detail"]
        with runtime.sessions() as session:
            assert session.query(Job).count() == 0  # no job for the refused upload
        filler.unlink()
        assert client.get("/readyz").status_code == 200
        assert client.post(f"/v1/calibration-sets/{calibration_id}/stereo", headers=headers, files=files,
                           data={"name": "recalibrated"}).status_code == 202


@pytest.mark.parametrize("stop", ["stop", pytest.param("kill", marks=pytest.mark.reliability)])  # kill: 1 min more
def test_rabbitmq_stopped_jobs_wait_in_the_outbox_and_run_once_when_it_returns(private_rabbitmq, tmp_path, stop):
    import dramatiq
    import pika

    from services.runtime import use_runtime
    from workers.middleware import JobBookkeeping

    schema = f"tf_outbox_{uuid.uuid4().hex[:10]}"
    queue_name = f"tf-outbox-{uuid.uuid4().hex[:8]}"
    runtime = _runtime(POSTGRES_URL, tmp_path, schema=schema, broker_url=private_rabbitmq.url, job_queue=queue_name,
                       min_free_bytes=0, job_queue_bound=6)
    headers = _key(runtime)
    try:
        with _client(runtime) as client:
            created = client.post("/v1/calibration-sets", headers=headers,
                                  files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                                  data={"name": "rig", "activate": "true"})
            assert created.status_code == 201, created.text
            first = client.post("/v1/scans", headers=headers).json()["job_id"]  # sent at once (and confirmed)
            getattr(private_rabbitmq, stop)()  # `rabbitmqctl stop`, or SIGKILL: the confirmed message survives
            started = time.monotonic()
            waiting = [client.post("/v1/scans", headers={**headers, "Idempotency-Key": f"k{i}"}) for i in range(4)]
            assert [response.status_code for response in waiting] == [202] * 4, [r.text for r in waiting]
            seconds_per_post = (time.monotonic() - started) / 4
            replay = client.post("/v1/scans", headers={**headers, "Idempotency-Key": "k0"})  # the MES retries
            assert replay.json() == waiting[0].json() and replay.headers["idempotent-replayed"] == "true"
            outbox = client.app.state.jobs
            assert outbox.pending() == 4  # committed, waiting for the broker; operators see it:
            assert "thermofield_jobs_undispatched 4.0" in client.get("/metrics").text
            assert client.post("/v1/scans", headers=headers).status_code == 202  # the 6th waiting job: the bound
            refused = client.post("/v1/scans", headers=headers)
            assert refused.status_code == 503 and refused.headers["content-type"] == PROBLEM
            assert refused.json()["type"].endswith("/queue-full") and int(refused.headers["retry-after"]) > 0
            private_rabbitmq.start()
            down_s = time.monotonic() - started
            deadline = time.monotonic() + 60  # the outbox's thread retries with backoff until the broker is back
            while outbox.pending() and time.monotonic() < deadline:
                time.sleep(0.2)
            assert outbox.pending() == 0
            sent_after_s = time.monotonic() - started - down_s
        with runtime.sessions() as session:
            jobs = {job.id: job for job in session.query(Job)}
        assert len(jobs) == 6 and first in jobs
        # A second copy of one message, as an outbox crash between sending and recording would leave.
        duplicated = waiting[1].json()["job_id"]
        JobQueue(job_broker(runtime.settings), queue_name).send("scan", duplicated)

        # A worker with the service's bookkeeping; its actor stands in for the scan's science.
        use_runtime(runtime)
        broker = job_broker(runtime.settings)
        broker.add_middleware(JobBookkeeping())
        runs: list[str] = []

        @dramatiq.actor(broker=broker, actor_name="scan", queue_name=queue_name, max_retries=0)
        def scan(job_id):
            runs.append(job_id)
            time.sleep(0.3)  # the test: the job's work takes a while

        worker = dramatiq.Worker(broker, worker_threads=2, worker_timeout=100)
        worker.start()
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                with runtime.sessions() as session:
                    if session.query(Job).filter(Job.status == "succeeded").count() == len(jobs):
                        break
                time.sleep(0.2)
            time.sleep(1.0)  # the test's window: a duplicate, if it were run, would run by now (no event tells)
        finally:
            worker.stop()
        assert sorted(runs) == sorted(jobs), runs  # every job ran, none twice
        with runtime.sessions() as session:
            assert {(job.status, job.attempts) for job in session.query(Job)} == {("succeeded", 1)}
        connection = pika.BlockingConnection(pika.URLParameters(private_rabbitmq.url))
        assert connection.channel().queue_declare(queue_name, passive=True).method.message_count == 0
        connection.close()
        print(f"\nRabbitMQ {stop}: down {down_s:.1f} s (with its restart): 4 jobs waited, {seconds_per_post * 1000:.0f} ms per POST; "
              f"outbox empty {sent_after_s:.1f} s after the broker was back; {len(runs)} runs of {len(jobs)} jobs")
    finally:
        runtime.engine.dispose()
        with make_engine(POSTGRES_URL).begin() as connection:
            connection.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))


@pytest.mark.reliability  # a minute: a RabbitMQ restart under a running job (make test-reliability)
def test_rabbitmq_restarted_under_a_running_job_does_not_run_it_twice(private_rabbitmq, tmp_path, caplog):
    import logging
    import threading

    import dramatiq

    from services.jobs.outbox import Outbox
    from services.runtime import use_runtime
    from workers.middleware import JobBookkeeping

    queue_name = f"tf-lease-{uuid.uuid4().hex[:8]}"
    runtime = _runtime(f"sqlite:///{tmp_path / 'service.db'}", tmp_path, broker_url=private_rabbitmq.url,
                       job_queue=queue_name)
    use_runtime(runtime)
    with runtime.sessions.begin() as session:
        job_id = runtime.tracker.create(session, "scan", {}).id
    assert Outbox(runtime.sessions, JobQueue(job_broker(runtime.settings), queue_name)).send(job_id)
    broker = job_broker(runtime.settings)
    broker.add_middleware(JobBookkeeping())
    runs: list[str] = []
    release = threading.Event()

    @dramatiq.actor(broker=broker, actor_name="scan", queue_name=queue_name, max_retries=0)
    def scan(job_id):  # stands in for a long scan: runs until the test has seen the redelivery wait
        runs.append(job_id)
        release.wait(120)

    caplog.set_level(logging.INFO, logger="workers.middleware")
    worker = dramatiq.Worker(broker, worker_threads=2, worker_timeout=100)  # a free thread takes the redelivery
    worker.start()
    try:
        deadline = time.monotonic() + 60
        while not runs and time.monotonic() < deadline:
            time.sleep(0.1)
        assert runs == [job_id]
        private_rabbitmq.stop()  # the worker's connection drops; the unacknowledged message goes back
        private_rabbitmq.start()
        deadline = time.monotonic() + 120
        while not any("waits" in record.getMessage() for record in caplog.records) and time.monotonic() < deadline:
            time.sleep(0.2)
        waited = [record.getMessage() for record in caplog.records if "waits" in record.getMessage()]
        assert waited and job_id in waited[0], caplog.text  # redelivered, but the job's lease was live
        release.set()
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            with runtime.sessions() as session:
                if session.get(Job, job_id).status == "succeeded":
                    break
            time.sleep(0.2)
        deadline = time.monotonic() + 60  # the waiting copy comes back (after half a lease) and finds it finished
        while not any("Skipping" in record.getMessage() for record in caplog.records) and time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        release.set()
        worker.stop()
    assert runs == [job_id], runs  # ran once, though RabbitMQ delivered its message again
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
        assert (job.status, job.attempts) == ("succeeded", 1)
    skipped = [record.getMessage() for record in caplog.records if "Skipping" in record.getMessage()]
    assert skipped, caplog.text
    print(f"\nRabbitMQ restarted under a running job: the redelivery waited {len(waited)} time(s), then was "
          f"skipped as finished; 1 run, attempts {job.attempts}")
