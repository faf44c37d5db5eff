"""The transactional outbox: a job's message leaves for the broker only after its row is committed, and a
job whose message could not be sent waits in the database until the broker takes it.

A new job is committed with ``dispatched_at`` unset (in the same transaction as its
scan and idempotency record). :meth:`Outbox.send` then hands the message to the
broker (publisher confirms on: the broker acknowledged it) and records
``dispatched_at``; when the broker is down the job stays pending and the outbox's
thread in the API process sends the pending jobs, oldest first, retrying with
exponential backoff until the broker is back. Several API processes may run one:
each pending row is claimed while it is sent (``FOR UPDATE SKIP LOCKED`` and a
conditional update on PostgreSQL; SQLite has one writer at a time).

A crash between the broker's acknowledgement and the commit of ``dispatched_at``
sends the message twice; the workers ignore the second (see
:meth:`services.jobs.tracker.JobTracker.start`). This is the usual outbox trade:
at least once from the outbox, exactly once by the consumer's check.
"""

from __future__ import annotations

import logging
import threading
from datetime import UTC, datetime

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import Job
from services.jobs.queue import JobQueue

logger = logging.getLogger(__name__)


class Outbox:
    """Sends the pending jobs of ``sessions`` to ``queue``, now (:meth:`send`) or from its thread.

    The thread (run while the API serves, ``with outbox:``) is woken after each new job
    whose request could not send it, and looks every ``poll_s`` for jobs another process
    left pending; while the broker is down it retries after ``min_backoff_s``, doubling
    up to ``max_backoff_s``.
    """

    def __init__(self, sessions: sessionmaker[Session], queue: JobQueue, poll_s: float = 5.0,
                 min_backoff_s: float = 0.5, max_backoff_s: float = 10.0) -> None:
        self.sessions, self.queue = sessions, queue
        self.poll_s, self.min_backoff_s, self.max_backoff_s = poll_s, min_backoff_s, max_backoff_s
        self._wake, self._stop = threading.Event(), threading.Event()
        self._thread: threading.Thread | None = None
        self.failing = False
        """True while the last attempt failed (broker or database down): new jobs then go straight to the
        thread instead of making their request wait on the broker first."""

    def send(self, job_id: str) -> bool:
        """Send job ``job_id``'s message unless it was sent already; False when it stays pending (the broker
        did not take it, or the outbox is failing): the thread will send it."""
        if not self.failing:
            try:
                with self.sessions.begin() as session:
                    job = session.scalar(self._pending().where(Job.id == job_id))
                    if job is not None:
                        self._dispatch(session, job)
                return True
            except Exception as error:  # any transport or database error leaves the job pending, never lost
                logger.warning("job %s waits in the outbox: %s", job_id, _describe(error))
        self._wake.set()
        return False

    def send_pending(self, batch: int = 100) -> int:
        """Send up to ``batch`` pending jobs, oldest first, one commit each; how many were looked at. A broker
        or database error propagates, after the jobs sent so far are recorded."""
        for done in range(batch):
            with self.sessions.begin() as session:
                job = session.scalar(self._pending().order_by(Job.created_at).limit(1))
                if job is None:
                    return done
                self._dispatch(session, job)
        return batch

    def pending(self) -> int:
        """How many jobs wait in the outbox."""
        with self.sessions() as session:
            return session.scalar(select(func.count()).select_from(Job).where(Job.dispatched_at.is_(None)))

    @staticmethod
    def _pending():
        return select(Job).where(Job.dispatched_at.is_(None)).with_for_update(skip_locked=True)

    def _dispatch(self, session: Session, job: Job) -> None:
        # Claimed by a conditional update (row-locked on PostgreSQL, the write lock on SQLite) so that two
        # senders never both send it; rolled back, and so pending again, when the broker refuses the message.
        claimed = session.execute(update(Job).where(Job.id == job.id, Job.dispatched_at.is_(None))
                                  .values(dispatched_at=datetime.now(UTC))).rowcount
        if claimed:
            self.queue.send(job.kind, job.id)

    def __enter__(self) -> Outbox:
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="outbox", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=10)

    def _run(self) -> None:
        backoff = self.min_backoff_s
        while not self._stop.is_set():
            self._wake.clear()
            try:
                while self.send_pending() and not self._stop.is_set():
                    pass
            except Exception as error:  # the broker or the database is down: try again later
                if not self.failing:
                    logger.warning("outbox: cannot send pending jobs (%s); retrying with backoff", _describe(error))
                self.failing = True
                self._stop.wait(backoff)
                backoff = min(backoff * 2, self.max_backoff_s)
                continue
            if self.failing:
                logger.warning("outbox: the pending jobs are sent")
            self.failing, backoff = False, self.min_backoff_s
            self._wake.wait(self.poll_s)


def _describe(error: BaseException) -> str:
    return f"{type(error).__name__}: {error}" if str(error) else type(error).__name__
