"""Jobs: status, progress and results; progress as server-sent events.

``GET /v1/jobs/{id}`` is what every client polls, so its path is kept short: the job is
read by :func:`services.db.jobs.load_job` with one SQL statement in autocommit, and the answer
is serialised once by its Pydantic model (FastAPI would validate and encode the returned model
a second time).
"""

from __future__ import annotations

import asyncio
import mimetypes
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response
from fastapi.sse import EventSourceResponse, ServerSentEvent

from api.deps import ReaderKey, RuntimeDep, SessionDep
from api.artifacts import stored_path
from api.problems import Problem, problem_responses
from api.schemas import JobOut
from services.db.jobs import JobRow, load_job, recent_jobs
from services.db.models import TERMINAL_STATUSES, Job
from services.jobs.tracker import job_state

router = APIRouter(prefix="/jobs", tags=["jobs"])
_POLL_INTERVAL_S = 0.1
_KEEPALIVE_S = 15.0


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


ExistingJob = Annotated[JobRow, Depends(_existing_job)]


@router.get("", name="list_jobs")
def list_jobs(session: SessionDep, _: ReaderKey, limit: Annotated[int, Query(ge=1, le=500)] = 50) -> list[JobOut]:
    """The most recent jobs, newest first."""
    return [job_out(job) for job in recent_jobs(session, limit)]


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
