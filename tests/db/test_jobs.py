import json
import threading
import uuid

import paho.mqtt.client as mqtt
import pytest

from services.db.apikeys import create_api_key, find_api_key, grants, parse_scopes
from services.db.engine import make_sessions
from services.db.models import Job
from services.events.mqtt import EventPublisher, job_topic
from services.jobs.tracker import JobTracker


def test_lifecycle_attempts_progress_and_result(engine):
    tracker = JobTracker(make_sessions(engine))
    with tracker.sessions.begin() as session:
        job_id = tracker.create(session, "scan", {"scan_id": "s1"}).id
    started = tracker.start(job_id, "host:1")
    assert (started.attempts, started.worker) == (1, "host:1")
    tracker.progress(job_id, "reconstruct", 0.4)
    tracker.fail(job_id, "GatewayError: lost", will_retry=True)
    with tracker.sessions() as session:
        job = session.get(Job, job_id)
        assert (job.status, job.stage, job.error) == ("queued", "retrying", "GatewayError: lost")
    assert tracker.start(job_id).attempts == 2
    tracker.succeed(job_id, {"field.ply": "abc"})
    with tracker.sessions() as session:
        job = session.get(Job, job_id)
        assert (job.status, job.fraction, job.result, job.error) == ("succeeded", 1.0, {"field.ply": "abc"}, None)
        assert job.finished_at is not None
    assert tracker.start(job_id) is None  # a duplicate delivery of a finished job is refused


def test_progress_fraction_is_checked(engine):
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        JobTracker(make_sessions(engine)).progress("any", "x", 1.5)


def test_recover_requeues_jobs_a_crash_left_unfinished(engine):
    tracker = JobTracker(make_sessions(engine))
    with tracker.sessions.begin() as session:
        running, queued, done = (tracker.create(session, "scan", {}).id for _ in range(3))
    tracker.start(running)
    tracker.start(done)
    tracker.succeed(done, {})
    recovered = {job.id for job in tracker.recover()}
    assert recovered == {running, queued}
    with tracker.sessions() as session:
        job = session.get(Job, running)
        assert (job.status, job.stage) == ("queued", "recovered")


def test_api_keys_are_stored_hashed_with_hierarchical_scopes(engine):
    sessions = make_sessions(engine)
    with sessions.begin() as session:
        key, secret = create_api_key(session, "mes", ["operate"])
        assert secret not in key.secret_sha256
    with sessions() as session:
        found = find_api_key(session, secret)
        assert found.id == key.id
        assert grants(found, "read") and grants(found, "operate") and not grants(found, "admin")
        assert find_api_key(session, secret + "x") is None
    with pytest.raises(ValueError, match="subset of read, operate, admin"):
        parse_scopes(["write"])


def test_state_changes_are_published_retained_to_mosquitto(engine):
    prefix = f"test-{uuid.uuid4().hex[:8]}/station1"
    publisher = EventPublisher("127.0.0.1", 1883, prefix)
    tracker = JobTracker(make_sessions(engine), publisher)
    with tracker.sessions.begin() as session:
        job_id = tracker.create(session, "scan", {"scan_id": "s9"}).id
    tracker.start(job_id)
    tracker.succeed(job_id, {"n": 1})
    publisher.close()

    received, done = {}, threading.Event()  # a late subscriber still gets the last (retained) state

    def on_message(client, userdata, message):
        received[message.topic] = (json.loads(message.payload), message.retain)
        if len(received) == 2:
            done.set()

    subscriber = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    subscriber.on_message = on_message
    subscriber.connect("127.0.0.1", 1883)
    subscriber.subscribe(f"{prefix}/#", qos=1)
    subscriber.loop_start()
    try:
        assert done.wait(10), received
    finally:
        for topic in received:
            subscriber.publish(topic, b"", retain=True)  # clear the retained test messages
        subscriber.loop_stop()
        subscriber.disconnect()
    state, retained = received[job_topic(prefix, job_id)]
    assert retained and state["status"] == "succeeded" and state["attempts"] == 1
    scan_state, _ = received[f"{prefix}/scans/s9"]
    assert scan_state["job_id"] == job_id and scan_state["status"] == "succeeded"
