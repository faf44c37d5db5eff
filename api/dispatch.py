"""Starting a job from a request: its row (and its scan's), the 202 answer, and the message after commit."""

from __future__ import annotations

from typing import Any

from sqlalchemy.orm import Session

from api.idempotency import Outcome
from api.schemas import Accepted
from services.db.models import Scan
from services.jobs.queue import JobQueue
from services.runtime import Runtime


def start_job(runtime: Runtime, queue: JobQueue, session: Session, kind: str, params: dict[str, Any],
              scan: Scan | None = None) -> Outcome:
    """Add a queued ``kind`` job (and ``scan``, which it produces) to ``session``; the outcome answers 202
    with the links to follow it, and once committed announces the job and sends it to its actor."""
    job = runtime.tracker.create(session, kind, params)
    links = {"job": f"/v1/jobs/{job.id}", "events": f"/v1/jobs/{job.id}/events"}
    if scan is not None:
        scan.job_id = job.id
        session.add(scan)
        links["scan"] = f"/v1/scans/{scan.id}"

    def dispatch() -> None:
        runtime.tracker.announce(job)
        queue.send(kind, job.id)

    accepted = Accepted(job_id=job.id, scan_id=params.get("scan_id"), status="queued", links=links)
    return Outcome(202, accepted.model_dump(mode="json"), links["job"], dispatch)
