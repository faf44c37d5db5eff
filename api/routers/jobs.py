"""Jobs: status, progress and results; progress as server-sent events.

``GET /v1/jobs/{id}`` is what every client polls, so its path is kept short: the job is
read by :func:`load_job` with one SQL statement in autocommit (no BEGIN and ROLLBACK round
trips) on a pooled DBAPI connection, and the answer is serialised once by its Pydantic model
(FastAPI would validate and encode the returned model a second time).
"""

from __future__ import annotations

import asyncio
import functools
import mimetypes
from collections import namedtuple
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response
from fastapi.sse import EventSourceResponse, ServerSentEvent
from sqlalchemy import Dialect, Engine, bindparam, select
from sqlalchemy.exc import DBAPIError

from api.deps import ReaderKey, RuntimeDep, SessionDep
from api.artifacts import stored_path
from api.problems import Problem, problem_responses
from api.schemas import JobOut
from services.db.models import TERMINAL_STATUSES, Job
from services.jobs.tracker import job_state

router = APIRouter(prefix="/jobs", tags=["jobs"])
_POLL_INTERVAL_S = 0.1
_KEEPALIVE_S = 15.0


JobRow = namedtuple("JobRow", ("id", "kind", "status", "stage", "fraction", "attempts", "worker", "error", "params",
                               "result", "created_at", "started_at", "finished_at"))
"""The columns of a job that its public state (:func:`services.jobs.tracker.job_state`) reads."""


def job_out(job: Job | JobRow) -> JobOut:
    links = {"self": f"/v1/jobs/{job.id}", "events": f"/v1/jobs/{job.id}/events"}
    for name in job.result.get("artifacts", {}):
        links[name] = f"/v1/jobs/{job.id}/artifacts/{name}"
    return JobOut(**job_state(job), links=links)


async def _existing_job(job_id: str, request: Request, _: ReaderKey) -> JobRow:
    job = await run_in_threadpool(load_job, request.app.state.runtime.engine, job_id)
    if job is None:
        raise Problem(404, "not-found", f"There is no job {job_id!r}.")
    return job


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


ExistingJob = Annotated[JobRow, Depends(_existing_job)]


@router.get("", name="list_jobs")
def list_jobs(session: SessionDep, _: ReaderKey, limit: Annotated[int, Query(ge=1, le=500)] = 50) -> list[JobOut]:
    """The most recent jobs, newest first."""
    return [job_out(job) for job in session.scalars(select(Job).order_by(Job.created_at.desc()).limit(limit))]


@router.get("/{job_id}", name="get_job", response_model=JobOut, responses=problem_responses(404))
async def get_job(job: ExistingJob) -> Response:
    """A job's status, progress (stage and fraction), attempts, error and result artifacts."""
    return Response(job_out(job).model_dump_json(), media_type="application/json")


@router.get("/{job_id}/events", name="stream_job_events", response_class=EventSourceResponse,
            responses=problem_responses(404))
async def stream_job_events(job: ExistingJob, runtime: RuntimeDep) -> AsyncIterator[ServerSentEvent]:
    """Server-sent events: a ``progress`` event at each change, then ``done`` when the job has finished."""
    last, idle = None, 0.0
    while True:
        state = await run_in_threadpool(_read_state, runtime, job.id)
        snapshot = (state["status"], state["stage"], state["fraction"], state["attempts"])
        if snapshot != last:
            last, idle = snapshot, 0.0
            finished = state["status"] in TERMINAL_STATUSES
            yield ServerSentEvent(data=state, event="done" if finished else "progress")
            if finished:
                return
        elif idle >= _KEEPALIVE_S:
            idle = 0.0
            yield ServerSentEvent(comment="keep-alive")
        await asyncio.sleep(_POLL_INTERVAL_S)
        idle += _POLL_INTERVAL_S


@router.get("/{job_id}/artifacts/{name}", name="download_job_artifact",
            responses={200: {"content": {"application/octet-stream": {}}}, **problem_responses(404)})
def download_job_artifact(job: ExistingJob, name: str, runtime: RuntimeDep) -> FileResponse:
    """A file the job produced, as listed in its ``result.artifacts`` (e.g. ``cloud.ply``, ``registration.json``)."""
    digest = job.result.get("artifacts", {}).get(name)
    if digest is None:
        raise Problem(404, "not-found", f"Job {job.id} has no artifact {name!r} "
                                        f"(it has: {', '.join(job.result.get('artifacts', {})) or 'none yet'}).")
    media_type = mimetypes.guess_type(name)[0] or "application/octet-stream"
    return FileResponse(stored_path(runtime.store, digest, f"job {job.id}"), media_type=media_type,
                        filename=f"{job.id}-{name}")


def _read_state(runtime, job_id: str) -> dict:
    return job_state(load_job(runtime.engine, job_id))
