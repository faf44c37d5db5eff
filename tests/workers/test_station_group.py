"""A station scan's heads as a Dramatiq group: the barrier in the database clears once, at the last head; the
scan job handed over waits at its stage, is taken up once by its continuation, and fails with a head that fails."""

import time

import dramatiq
import pytest
from dramatiq import Worker

from services.db.engine import make_sessions
from services.db.models import Job
from services.jobs.barrier import DatabaseBarrierBackend
from services.jobs.tracker import CONTINUATION, CONTINUED, JobTracker
from dramatiq.rate_limits import Barrier


def test_the_barrier_clears_at_its_last_party_only(engine):
    backend = DatabaseBarrierBackend(lambda: make_sessions(engine))
    barrier = Barrier(backend, "group-1", ttl=60_000)
    assert barrier.create(3) and not barrier.create(3)  # a key is created once
    assert [barrier.wait(block=False) for _ in range(3)] == [False, False, True]
    other = Barrier(backend, "group-2", ttl=60_000)
    assert other.create(1) and other.wait(block=False)  # a group of one clears at once


def _job(sessions, **params) -> str:
    with sessions.begin() as session:
        job = JobTracker(sessions).create(session, "scan", params)
        return job.id


def test_a_handed_over_job_waits_and_is_taken_up_once_by_its_continuation(engine):
    sessions = make_sessions(engine)
    tracker = JobTracker(sessions)
    job_id = _job(sessions)
    assert tracker.start(job_id, "w:1") is not None
    assert tracker.start(job_id, "w:2", continuation=True) is None  # not handed over yet: its lease is live
    tracker.hand_over(job_id, {"artifacts": {"a": "1"}, CONTINUED: {"stage": "heads", "fraction": 0.3}})
    with sessions() as session:
        job = session.get(Job, job_id)
        assert (job.status, job.stage, job.result) == ("running", "heads", {"artifacts": {"a": "1"}})
    assert tracker.start(job_id, "w:3") is None  # a second copy of the first message is skipped
    taken = tracker.start(job_id, "w:4", continuation=True)
    assert taken is not None and taken.attempts == 1 and taken.worker == "w:4"
    assert tracker.start(job_id, "w:5", continuation=True) is None  # taken up once


def test_a_head_that_fails_for_good_fails_its_scan(engine):
    sessions = make_sessions(engine)
    tracker = JobTracker(sessions)
    scan = _job(sessions)
    with sessions.begin() as session:
        head = tracker.create(session, "scan_head", {"parent_job_id": scan, "head": "head-2"}).id
    tracker.fail(head, "StorageFull: no space", will_retry=False)
    with sessions() as session:
        failed = session.get(Job, scan)
        assert failed.status == "failed" and failed.error == "head 'head-2' failed: StorageFull: no space"


def test_a_group_of_jobs_sends_its_completion_once_after_every_member_is_recorded(broker, monkeypatch):
    """Even when recording a member's result is slow: Dramatiq runs the middleware's after-hooks in reverse, so the
    group callbacks must come before the bookkeeping in the list, or another worker thread runs the completion
    while the last member is still ``running``."""
    from services.runtime import current_runtime

    sessions = current_runtime().sessions
    tracker = current_runtime().tracker
    recorded = tracker.succeed

    def slowly_recorded(job_id, result):
        time.sleep(0.3)
        return recorded(job_id, result)

    monkeypatch.setattr(tracker, "succeed", slowly_recorded)
    seen: list[tuple[str, list[str]]] = []

    @dramatiq.actor(actor_name="member", broker=broker, queue_name="default")
    def member(job_id: str) -> dict:
        return {"value": job_id}

    @dramatiq.actor(actor_name="completion", broker=broker, queue_name="default")
    def completion(job_id: str) -> dict:
        with sessions() as session:
            members = session.query(Job).filter(Job.kind == "member").all()
            seen.append((job_id, sorted(job.status for job in members)))
        return {}

    members = [_job(sessions) for _ in range(3)]
    with sessions.begin() as session:
        for job in session.query(Job).filter(Job.id.in_(members)):
            job.kind = "member"
    parent = _job(sessions)
    tracker.start(parent, "w:1")
    tracker.hand_over(parent, {CONTINUED: {"stage": "heads", "fraction": 0.3}})
    group = dramatiq.group([member.message(job) for job in members])
    group.add_completion_callback(completion.message_with_options(args=(parent,), **{CONTINUATION: True}))
    group.run()
    worker = Worker(broker, worker_timeout=50)
    worker.start()
    try:
        broker.join("default")
        worker.join()
    finally:
        worker.stop()
    assert seen == [(parent, ["succeeded"] * 3)]
    with sessions() as session:
        assert session.get(Job, parent).status == "succeeded"


def test_a_restart_sends_a_waiting_station_scan_again_and_fails_its_heads(engine):
    sessions = make_sessions(engine)
    tracker = JobTracker(sessions)
    scan = _job(sessions, scan_id="s1")
    tracker.start(scan, "w:1")
    tracker.hand_over(scan, {CONTINUED: {"stage": "heads", "fraction": 0.3}})
    with sessions.begin() as session:
        head = tracker.create(session, "scan_head", {"parent_job_id": scan, "head": "head-1"}).id
    tracker.recover()
    with sessions() as session:
        again, lost = session.get(Job, scan), session.get(Job, head)
        assert (again.status, again.dispatched_at) == ("queued", None)  # the outbox sends it: captured anew
        assert lost.status == "failed" and "restart" in lost.error
    assert tracker.start(scan, "w:2") is not None


def test_a_continuation_that_fails_is_retried_as_any_message(engine):
    sessions = make_sessions(engine)
    tracker = JobTracker(sessions)
    job_id = _job(sessions)
    tracker.start(job_id, "w:1")
    tracker.hand_over(job_id, {CONTINUED: {"stage": "heads", "fraction": 0.3}})
    assert tracker.start(job_id, "w:2", continuation=True) is not None
    tracker.fail(job_id, "RuntimeError: merge", will_retry=True)
    retried = tracker.start(job_id, "w:3", continuation=True)  # the retry's copy carries the option too
    assert retried is not None and retried.attempts == 2 and retried.status == "running"
