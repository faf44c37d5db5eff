import json
import threading
import time
import uuid

import paho.mqtt.client as mqtt
import pytest

from services.db.apikeys import create_api_key, find_api_key, grants, parse_scopes
from services.db.engine import make_sessions
from services.db.models import Job
from services.events.mqtt import EventPublisher, job_topic, station_topic
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


def _subscriber(prefix: str, received: list) -> mqtt.Client:
    """A client subscribed to everything under ``prefix``; its ``subscribed`` event is set when the broker has
    acknowledged the subscription (and so has queued the retained messages for it)."""
    subscriber = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
    subscriber.on_message = lambda client, userdata, message: received.append(
        (message.topic, json.loads(message.payload) if message.payload else None, message.retain))
    subscriber.subscribed = threading.Event()
    subscriber.on_subscribe = lambda *_: subscriber.subscribed.set()
    subscriber.connect("127.0.0.1", 1883)
    subscriber.subscribe(f"{prefix}/#", qos=1)
    subscriber.loop_start()
    return subscriber


def _wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)


def test_states_are_published_live_and_only_the_stations_latest_is_retained(engine):
    prefix = f"test-{uuid.uuid4().hex[:8]}/station1"
    live: list = []
    listener = _subscriber(prefix, live)
    publisher = EventPublisher("127.0.0.1", 1883, prefix)
    tracker = JobTracker(make_sessions(engine), publisher)
    assert listener.subscribed.wait(10)
    job_ids = []
    for scan_id in ("s8", "s9"):
        with tracker.sessions.begin() as session:
            job_ids.append(tracker.create(session, "scan", {"scan_id": scan_id}).id)
        tracker.start(job_ids[-1])
        tracker.succeed(job_ids[-1], {"n": 1})
    publisher.close()
    late: list = []  # a subscriber that connects afterwards gets one retained message: the station's latest
    latecomer = _subscriber(prefix, late)
    try:
        assert latecomer.subscribed.wait(10)
        # The broker sends a subscription's retained messages before anything published after it: once the
        # latecomer hears its own marker, every retained message has come.
        marker = f"{prefix}/marker"
        latecomer.publish(marker, b"", qos=1).wait_for_publish(5)
        _wait_for(lambda: len(live) >= 9 and any(topic == marker for topic, _, _ in late))
    finally:
        latecomer.publish(station_topic(prefix), b"", retain=True).wait_for_publish(5)
        for client in (listener, latecomer):
            client.loop_stop()
            client.disconnect()
    job_states = [state["status"] for topic, state, _ in live if topic == job_topic(prefix, job_ids[1])]
    assert job_states == ["running", "succeeded"]
    assert [state["status"] for topic, state, _ in live if topic == f"{prefix}/scans/s9"] == ["running", "succeeded"]
    assert not any(retained for _, _, retained in live)
    late = [message for message in late if message[1] is not None]  # not the marker, nor the clearing of the
    # test's retained message
    assert [(topic, retained) for topic, _, retained in late] == [(station_topic(prefix), True)]
    assert late[0][1]["scan_id"] == "s9" and late[0][1]["status"] == "succeeded" and late[0][1]["job_id"] == job_ids[1]


def test_a_second_message_for_a_running_job_is_refused_unless_redelivered_after_its_lease(engine):
    from datetime import UTC, datetime, timedelta

    from services.jobs.tracker import LEASE_S, JobBusy

    tracker = JobTracker(make_sessions(engine))
    with tracker.sessions.begin() as session:
        job_id = tracker.create(session, "scan", {}).id
    assert tracker.start(job_id, "host:1").attempts == 1
    assert tracker.start(job_id, "host:2") is None  # a duplicate copy while the first runs: skipped
    with pytest.raises(JobBusy, match="host:1"):  # redelivered, but host:1 holds the lease: not yet
        tracker.start(job_id, "host:2", redelivered=True)
    with tracker.sessions.begin() as session:  # host:1 died: its last heartbeat grows old
        session.get(Job, job_id).heartbeat_at = datetime.now(UTC) - timedelta(seconds=LEASE_S + 1)
    tracker.beat(job_id, "host:2")  # not its attempt: renews nothing
    rerun = tracker.start(job_id, "host:2", redelivered=True)
    assert (rerun.attempts, rerun.worker) == (2, "host:2")
    with tracker.sessions.begin() as session:
        session.get(Job, job_id).heartbeat_at = datetime.now(UTC) - timedelta(seconds=LEASE_S + 1)
    tracker.beat(job_id, "host:2")  # host:2 renews its lease
    with pytest.raises(JobBusy):
        tracker.start(job_id, "host:3", redelivered=True)
    tracker.succeed(job_id, {})
    assert tracker.start(job_id, "host:3", redelivered=True) is None  # finished: never again
