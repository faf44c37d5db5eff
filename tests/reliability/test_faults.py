"""Faults against real servers of the test's own: PostgreSQL stopped and restarted under the API, Mosquitto
stopped while jobs change state, the artifact store's disk full under uploads."""

from __future__ import annotations

import json
import time

import paho.mqtt.client as mqtt
import pytest

from services.db.apikeys import create_api_key
from services.db.engine import make_engine, make_sessions, migrate
from services.db.models import IdempotencyRecord, Job
from services.events.mqtt import EventPublisher, station_topic
from services.formats.rig import rig_to_json
from services.jobs.tracker import JobTracker
from services.settings import Settings
from services.simulation.presets import forging_rig
from services.storage.artifacts import ArtifactStore
from services.jobs.queue import JobQueue, job_broker
from services.runtime import Runtime

PROBLEM = "application/problem+json"


def _client(runtime):
    from fastapi.testclient import TestClient

    from api.app import create_app



    return TestClient(create_app(runtime, JobQueue(job_broker(runtime.settings), runtime.settings.job_queue)),
                      raise_server_exceptions=False)


def _runtime(url: str, tmp_path, **settings) -> Runtime:
    engine = make_engine(url)
    migrate(engine)
    sessions = make_sessions(engine)
    config = Settings(data_dir=tmp_path, broker_url="", mqtt_host="", **settings)
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
            for method, path in (("GET", "/v1/jobs"), ("GET", "/v1/scans"), ("POST", "/v1/scans"),
                                 ("GET", "/v1/calibration-sets")):
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
    with runtime.sessions() as session:
        assert session.query(Job).count() == 1 and session.query(IdempotencyRecord).count() == 1


def _listen(port: int, prefix: str, received: list) -> mqtt.Client:
    client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    client.on_message = lambda c, u, message: received.append(
        (message.topic, json.loads(message.payload), bool(message.retain)))
    client.connect("127.0.0.1", port)
    client.subscribe(f"{prefix}/#", qos=1)
    client.loop_start()
    return client


def test_mosquitto_stopped_jobs_go_on_and_states_arrive_when_it_returns(private_mosquitto, tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
    migrate(engine)
    prefix = "fault/station1"
    publisher = EventPublisher("127.0.0.1", private_mosquitto.port, prefix)
    tracker = JobTracker(make_sessions(engine), publisher)
    with tracker.sessions.begin() as session:
        job_id = tracker.create(session, "scan", {"scan_id": "s1"}).id
    tracker.start(job_id)
    private_mosquitto.stop()
    stages = ["capture", "reconstruct", "fuse", "store"]
    for index, stage in enumerate(stages):  # the job goes on while the broker is down
        tracker.progress(job_id, stage, index / len(stages))
    tracker.succeed(job_id, {"artifacts": {}})
    with tracker.sessions() as session:
        assert session.get(Job, job_id).status == "succeeded"  # the database is the source of truth
    private_mosquitto.start()
    received: list = []
    deadline = time.monotonic() + 30  # the publisher reconnects and delivers what it queued, in order
    listener = None
    try:
        while time.monotonic() < deadline:
            if listener is None and publisher._client.is_connected():
                time.sleep(2.0)  # let the queued messages go out before a late subscriber connects
                listener = _listen(private_mosquitto.port, prefix, received)
            if any(topic == station_topic(prefix) for topic, _, _ in received):
                break
            time.sleep(0.1)
        time.sleep(0.5)
    finally:
        publisher.close()
        if listener is not None:
            listener.loop_stop()
            listener.disconnect()
    retained = [(state, retain) for topic, state, retain in received if topic == station_topic(prefix)]
    assert retained and retained[0][1], received  # a late subscriber gets the station's state, retained...
    assert retained[0][0]["status"] == "succeeded" and retained[0][0]["job_id"] == job_id  # ... the last one


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
