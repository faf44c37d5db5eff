"""Job lifecycle in the database: queued -> running -> succeeded | failed, with progress and retries.

Every change is committed at once (so the API, SSE streams and other processes see
it) and then published over MQTT when a publisher is configured. A job whose
attempt fails but will be retried goes back to ``queued`` with the error kept.
Jobs that a crash left ``queued`` or ``running`` are found by :meth:`JobTracker.recover`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import TERMINAL_STATUSES, Job, Scan
from services.events.mqtt import EventPublisher, job_topic, scan_topic, station_topic

logger = logging.getLogger(__name__)

LEASE_S = 10.0
"""A running job whose worker has not renewed its heartbeat for this long is taken to have lost it (the
worker renews it every ``LEASE_S / 5``; the hosts' clocks must agree to well within it)."""


CONTINUED = "continued"
"""The key of a result that hands its job over to later messages (a station scan's heads, then its merge): the
job stays ``running`` at the stage it names until a continuation message (:data:`CONTINUATION` in its options)
takes it up and finishes it."""
CONTINUATION = "continuation"


class JobBusy(Exception):
    """The job runs elsewhere under a live lease: a redelivered message must wait (the broker's connection to
    that worker dropped, the worker did not)."""


def utc_timestamp(moment: datetime | None) -> str | None:
    """ISO 8601 in UTC with a ``Z``, as the API's pydantic bodies write it, so that GET, SSE and MQTT agree."""
    if moment is None:
        return None
    return (moment if moment.tzinfo else moment.replace(tzinfo=UTC)).astimezone(UTC).isoformat().replace("+00:00", "Z")


def job_state(job: Job) -> dict[str, Any]:
    """The public state of a job (the API body and the MQTT payload share it)."""
    return {
        "job_id": job.id,
        "kind": job.kind,
        "status": job.status,
        "stage": job.stage,
        "fraction": round(job.fraction, 4),
        "attempts": job.attempts,
        "worker": job.worker,
        "error": job.error,
        "result": job.result,
        "scan_id": job.params.get("scan_id"),
        "created_at": utc_timestamp(job.created_at),
        "started_at": utc_timestamp(job.started_at),
        "finished_at": utc_timestamp(job.finished_at),
    }


class JobTracker:
    """Records job state changes in the database and announces them: over MQTT (``publisher``) and to the
    ``listeners`` (e.g. the OPC UA server), each called with the job's state and never allowed to fail a job."""

    def __init__(self, sessions: sessionmaker[Session], publisher: EventPublisher | None = None) -> None:
        self.sessions = sessions
        self.publisher = publisher
        self.listeners: list[Callable[[dict[str, Any]], None]] = []

    def create(self, session: Session, kind: str, params: dict[str, Any]) -> Job:
        """Add a queued job to ``session`` (the caller commits, then calls :meth:`announce`)."""
        job = Job(kind=kind, params=params)
        session.add(job)
        session.flush()
        return job

    def start(self, job_id: str, worker: str | None = None, redelivered: bool = False,
              continuation: bool = False) -> Job | None:
        """Mark an attempt as running (by ``worker``, host:pid) and take its lease; None when the job is
        unknown, already finished, or running and this message is not a redelivery.

        A job is ``running`` when a message arrives in three cases: the broker redelivers the
        message of a worker that died (``redelivered``, the lease ran out: run it again); it
        redelivers the message of a worker whose connection dropped but which still runs the
        job (``redelivered``, the lease is live: :class:`JobBusy`, try again later); or the
        message is a second copy (an outbox crash between sending and recording it) while the
        first runs (skip it: should that worker die, its own copy is redelivered).

        Raises
        ------
        JobBusy
            For a redelivery while the job's lease is live.

        A ``continuation`` message takes up a job handed over (:meth:`hand_over`) and waiting at its stage (the
        same attempt); once taken up, another copy is skipped, and its retries and redeliveries are started as
        any message's.
        """
        with self.sessions.begin() as session:
            job = session.get(Job, job_id, with_for_update=True)
            now = datetime.now(UTC)
            if continuation and job is not None and job.status == "running" and job.heartbeat_at is None:
                job.stage, job.worker, job.heartbeat_at = "continuing", worker, now  # handed over: take it up
            else:  # a first attempt, a retry (of a continuation too), a redelivery
                if job is None or job.status in TERMINAL_STATUSES or (job.status == "running" and not redelivered):
                    return None
                if job.status == "running" and job.heartbeat_at and job.heartbeat_at > now - timedelta(seconds=LEASE_S):
                    raise JobBusy(f"job {job_id} runs on {job.worker} (heartbeat {job.heartbeat_at.isoformat()})")
                job.status, job.stage, job.fraction = "running", "starting", 0.0
                job.attempts += 1
                job.started_at = job.heartbeat_at = now
                job.worker = worker
        self.announce(job)
        return job

    def beat(self, job_id: str, worker: str | None) -> None:
        """Renew the lease of ``worker``'s running attempt (nothing if the job moved on meanwhile)."""
        with self.sessions.begin() as session:
            session.execute(update(Job).where(Job.id == job_id, Job.status == "running", Job.worker == worker)
                            .values(heartbeat_at=datetime.now(UTC)))

    def progress(self, job_id: str, stage: str, fraction: float) -> None:
        if not 0.0 <= fraction <= 1.0:
            raise ValueError(f"Progress fraction must lie in [0, 1]; got {fraction}.")
        self._update(job_id, stage=stage, fraction=fraction)

    def succeed(self, job_id: str, result: dict[str, Any]) -> None:
        """Record the result; a scan job's ``artifacts``, ``summary`` and (inspected) ``verdict`` and ``features``
        go onto its scan in the same commit."""
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None:
                raise KeyError(f"job {job_id} does not exist")
            job.status, job.stage, job.fraction, job.result, job.error = "succeeded", "done", 1.0, result, None
            job.finished_at = datetime.now(UTC)
            scan = session.get(Scan, job.params["scan_id"]) if job.kind == "scan" and "scan_id" in job.params else None
            if scan is not None:
                scan.artifacts, scan.summary = result.get("artifacts", {}), result.get("summary")
                scan.verdict, scan.features = result.get("verdict"), result.get("features")
        self.announce(job)

    def hand_over(self, job_id: str, result: dict[str, Any]) -> None:
        """The job's message handed its job over to later ones (its result holds :data:`CONTINUED`: the stage it
        waits at, the fraction done): the job stays ``running`` at that stage without a lease, its partial
        result kept; a scan job's artifacts so far go onto its scan (nothing stored is lost if it later fails)."""
        waiting = result[CONTINUED]
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None:
                raise KeyError(f"job {job_id} does not exist")
            job.stage, job.fraction = waiting["stage"], waiting["fraction"]
            job.result, job.heartbeat_at = {k: v for k, v in result.items() if k != CONTINUED}, None
            scan = session.get(Scan, job.params["scan_id"]) if job.kind == "scan" and "scan_id" in job.params else None
            if scan is not None:
                scan.artifacts = result.get("artifacts", {})
        self.announce(job)

    def fail(self, job_id: str, error: str, will_retry: bool) -> None:
        if will_retry:
            self._update(job_id, status="queued", stage="retrying", error=error)
        else:
            self._update(job_id, status="failed", stage="failed", error=error, finished_at=datetime.now(UTC))
            with self.sessions() as session:
                job = session.get(Job, job_id)
                parent = None if job is None else job.params.get("parent_job_id")
                head = None if job is None else job.params.get("head")
            if parent is not None:  # a station scan's head: its scan cannot be finished without it
                self._update(parent, status="failed", stage="failed", finished_at=datetime.now(UTC),
                             error=f"head {head!r} failed: {error}")

    def recover(self) -> list[Job]:
        """Jobs a crash of the embedded service left unfinished (their messages died with its in-memory
        broker), put back to ``queued`` and into the outbox to be sent again; a station scan's head jobs are
        failed instead (their group died with the broker: their scan job, sent again, captures anew)."""
        with self.sessions.begin() as session:
            jobs = list(session.scalars(select(Job).where(Job.status.in_(("queued", "running")))))
            for job in jobs:
                if job.params.get("parent_job_id"):  # a station scan's head: its scan job runs again, whole
                    job.status, job.stage, job.finished_at = "failed", "failed", datetime.now(UTC)
                    job.error = "interrupted by a restart (its scan job runs again)"
                    continue
                job.dispatched_at = None
                if job.status == "running":
                    job.status, job.stage, job.error = "queued", "recovered", "interrupted by a restart"
        for job in jobs:
            self.announce(job)
        return jobs

    def announce(self, job: Job) -> None:
        """Publish the job's state, and its scan's when it is a scan job; the latter (or the job's) is also
        the station's state, the one retained message (a station scan's head job publishes its own state only).
        Then the listeners get the job's state."""
        state = job_state(job)
        for listener in self.listeners:
            try:
                listener(state)
            except Exception:
                logger.exception("a job-state listener failed")
        if self.publisher is None:
            return
        prefix = self.publisher.prefix
        self.publisher.publish(job_topic(prefix, job.id), state)
        if job.params.get("parent_job_id"):  # a station scan's head: its scan's and the station's state are the scan job's
            return
        scan_id = job.params.get("scan_id")
        if scan_id is not None:
            if job.kind == "scan":
                outputs = {"summary": job.result.get("summary"), "verdict": job.result.get("verdict")}
            else:
                outputs = self._scan_outputs(scan_id)
            state = {"scan_id": scan_id, **{k: v for k, v in state.items() if k != "scan_id"}, **outputs}
            self.publisher.publish(scan_topic(prefix, scan_id), state)
        self.publisher.publish(station_topic(prefix), state, retain=True)

    def _scan_outputs(self, scan_id: str) -> dict[str, Any]:
        with self.sessions() as session:
            scan = session.get(Scan, scan_id)
            return {"summary": None, "verdict": None} if scan is None else {"summary": scan.summary,
                                                                            "verdict": scan.verdict}

    def _update(self, job_id: str, **changes: Any) -> None:
        with self.sessions.begin() as session:
            job = session.get(Job, job_id)
            if job is None:
                raise KeyError(f"job {job_id} does not exist")
            for name, value in changes.items():
                setattr(job, name, value)
        self.announce(job)
