"""Starting a job from a request: its row (and its scan's), the 202 answer, and the message after commit.

The job is committed into the outbox (:mod:`services.jobs.outbox`) with the request's other rows; its
message is sent once the commit succeeded, now or, while the broker is down, by the outbox's thread. No
more than ``THERMOFIELD_JOB_QUEUE_BOUND`` jobs wait at once: beyond it a new job is refused with 503.
"""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from api.idempotency import Outcome
from api.problems import RETRY_AFTER_S, Problem
from api.schemas import Accepted
from services.db.models import Scan
from services.jobs.outbox import Outbox
from services.jobs.scans import JobRefused, check_queue_bound
from services.runtime import Runtime


def start_job(runtime: Runtime, queue: Outbox, session: Session, kind: str, params: dict[str, Any],
              scan: Scan | None = None) -> Outcome:
    """Add a queued ``kind`` job (and ``scan``, which it produces) to ``session``; the outcome answers 202
    with the links to follow it, and once committed announces the job and sends it to its actor.

    Raises
    ------
    Problem
        503 ``queue-full`` (with ``Retry-After``) when ``THERMOFIELD_JOB_QUEUE_BOUND`` jobs already wait.
    """
    try:
        check_queue_bound(session, runtime.settings.job_queue_bound)
    except JobRefused as refused:
        raise refused_problem(refused) from None
    job = runtime.tracker.create(session, kind, params)
    links = {"job": f"/v1/jobs/{job.id}", "events": f"/v1/jobs/{job.id}/events"}
    if scan is not None:
        scan.job_id = job.id
        session.add(scan)
        links["scan"] = f"/v1/scans/{scan.id}"

    def dispatch() -> None:
        runtime.tracker.announce(job)
        queue.send(job.id)

    accepted = Accepted(job_id=job.id, scan_id=params.get("scan_id"), status="queued", links=links)
    return Outcome(202, accepted.model_dump(mode="json"), links["job"], dispatch)


def refused_problem(refused: JobRefused) -> Problem:
    """The problem answering a job the station refused (503s say when to retry). The statuses are literals, so
    that tests/api/test_declared_statuses.py reads them from the code."""
    if refused.kind == "queue-full":
        return Problem(503, refused.kind, str(refused), {"Retry-After": str(RETRY_AFTER_S)})
    if refused.kind in ("no-active-calibration", "not-ready"):
        return Problem(409, refused.kind, str(refused))
    return Problem(422, refused.kind, str(refused))
