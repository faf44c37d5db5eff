"""Jobs' rows as the API reads them: one job's state on the path every client polls, the most recent jobs.

``GET /v1/jobs/{id}`` is what every client polls, so its path is kept short: the job is read by
:func:`load_job` with one SQL statement in autocommit (no BEGIN and ROLLBACK round trips) on a pooled DBAPI
connection.
"""

from __future__ import annotations

import functools
from collections import namedtuple
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from sqlalchemy import Dialect, Engine, bindparam, select
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import Job


JobRow = namedtuple("JobRow", ("id", "kind", "status", "stage", "fraction", "attempts", "worker", "error", "params",
                               "result", "created_at", "started_at", "finished_at"))
"""The columns of a job that its public state (:func:`services.jobs.tracker.job_state`) reads."""


@dataclass
class _JobQuery:
    sql: str
    positional: tuple[str, ...] | None  # the parameters' order for a positional paramstyle (SQLite's ``?``)
    types: tuple[Any, ...]  # the columns' SQLAlchemy types for this dialect
    processors: tuple[Callable[[Any], Any] | None, ...] | None = None  # each type's conversion of the driver's value,
    # found from the driver's type codes of the first result (the same on every connection)

    def convert(self, dialect: Dialect, cursor: Any, row: tuple) -> JobRow:
        if self.processors is None:
            self.processors = tuple(kind.result_processor(dialect, description[1])
                                    for kind, description in zip(self.types, cursor.description))
        return JobRow._make(value if process is None else process(value)
                            for process, value in zip(self.processors, row))


@functools.lru_cache(maxsize=8)
def _job_query(dialect: Dialect) -> _JobQuery:
    table = Job.__table__
    columns = [table.c[name] for name in JobRow._fields]
    compiled = select(*columns).where(table.c.id == bindparam("job_id")).compile(dialect=dialect)
    return _JobQuery(str(compiled), tuple(compiled.positiontup) if compiled.positional else None,
                     tuple(column.type.dialect_impl(dialect) for column in columns))


def load_job(engine: Engine, job_id: str) -> JobRow | None:
    """The job's state columns, or None.

    Every poll pays SQLAlchemy's per-execution work (execution context, result metadata,
    ``Row``) several times over the driver's own, so the statement, compiled once per
    dialect by SQLAlchemy, runs on the pool's DBAPI connection (pre-pinged like any
    checkout), and each value goes through its column type's result processor: the same
    values as a Core select gives on every database. A driver error is raised as
    SQLAlchemy's (``OperationalError`` -> 503 ``database-unavailable``), a lost connection
    invalidated.
    """
    dialect = engine.dialect
    query = _job_query(dialect)
    parameters = {"job_id": job_id}
    arguments = parameters if query.positional is None else tuple(parameters[name] for name in query.positional)
    connection = None
    try:
        connection = engine.raw_connection()
        dialect.set_isolation_level(connection.dbapi_connection, "AUTOCOMMIT")
        try:
            cursor = connection.cursor()
            cursor.execute(query.sql, arguments)
            row = cursor.fetchone()
            job = None if row is None else query.convert(dialect, cursor, row)
            cursor.close()
        finally:
            dialect.reset_isolation_level(connection.dbapi_connection)
    except dialect.loaded_dbapi.Error as error:
        lost = connection is not None and dialect.is_disconnect(error, connection.dbapi_connection, None)
        if lost:
            connection.invalidate(error)
        raise DBAPIError.instance(query.sql, parameters, error, dialect.loaded_dbapi.Error,
                                  connection_invalidated=lost, dialect=dialect) from error
    finally:
        if connection is not None:
            connection.close()
    return job


def recent_jobs(session: Session, limit: int) -> list[Job]:
    """The most recent jobs, newest first."""
    return list(session.scalars(select(Job).order_by(Job.created_at.desc()).limit(limit)))


def job(session: Session, job_id: str) -> Job | None:
    return session.get(Job, job_id)


def job_params(sessions: sessionmaker[Session], job_id: str) -> dict[str, Any]:
    """A job's parameters, as its worker reads them; ``LookupError`` when there is no such job."""
    with sessions() as session:
        row = session.get(Job, job_id)
        if row is None:
            raise LookupError(f"there is no job {job_id!r}")
        return dict(row.params)


def job_results(sessions: sessionmaker[Session], job_ids: list[str]) -> dict[str, dict[str, Any]]:
    """The results so far of jobs (a station scan's own, handed over; its heads'), by id; ``LookupError`` when one
    is missing."""
    with sessions() as session:
        rows = {row.id: dict(row.result or {}) for row in session.scalars(select(Job).where(Job.id.in_(job_ids)))}
    missing = [job_id for job_id in job_ids if job_id not in rows]
    if missing:
        raise LookupError(f"there is no job {missing[0]!r}")
    return rows


def add_child_jobs(sessions: sessionmaker[Session], kind: str, params: list[dict[str, Any]]) -> list[str]:
    """Add queued jobs of ``kind`` that their creator sends itself (a station scan's heads, as one Dramatiq group):
    marked dispatched, so that the outbox never sends them a second time outside their group. Their ids."""
    from datetime import UTC, datetime

    with sessions.begin() as session:
        jobs = [Job(kind=kind, params=one, dispatched_at=datetime.now(UTC)) for one in params]
        session.add_all(jobs)
        session.flush()
        return [job.id for job in jobs]
