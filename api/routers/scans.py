"""Scans: start one (202 + job), read its metadata, summary and verdict, download its artifacts."""

from __future__ import annotations

import re
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, Response

from api.deps import JobQueueDep, OperatorKey, ReaderKey, RuntimeDep, SessionDep
from api.dispatch import refused_problem, start_job
from api.idempotency import IdempotencyKeyHeader, Outcome, request_digest, respond_once
from api.artifacts import stored_path
from api.problems import Problem, problem_responses
from api.schemas import Accepted, ScanJobRequest, ScanOut, ScanRequest
from services.db import scans
from services.db.models import TERMINAL_STATUSES, Job, Scan
from services.formats.images import encode_frame
from services.formats.stored_scan import FRAMES, SERVED, THERMAL
from services.jobs.scans import JobRefused, new_scan, scan_inputs, scan_job_params, stored_scan_job_params

router = APIRouter(prefix="/scans", tags=["scans"])

ARTIFACT_NAME_PATTERN = "^(" + "|".join(re.escape(name) for name in SERVED) + ")$"
# One frame of a stored stack, as the image it was: the stack's artifact, the frame's media type and suffix.
FRAME_KINDS = {"frames": (FRAMES, "image/png", "png"), "thermal": (THERMAL, "image/tiff", "tiff")}


def scan_links(scan: Scan) -> dict[str, str]:
    links = {"self": f"/v1/scans/{scan.id}", "job": f"/v1/jobs/{scan.job_id}",
             "calibration_set": f"/v1/calibration-sets/{scan.calibration_set_id}"}
    if scan.part_type_id is not None:
        links["part_type"] = f"/v1/part-types/{scan.part_type_id}"
    for name in SERVED:
        if name in scan.artifacts:
            links[name] = f"/v1/scans/{scan.id}/{name}"
    for kind, (stack, _, suffix) in FRAME_KINDS.items():
        if stack.name in scan.artifacts:
            links[kind] = f"/v1/scans/{scan.id}/{kind}/{{index}}.{suffix}"
    return links


def _existing_scan(scan_id: str, session: SessionDep, _: ReaderKey) -> Scan:
    scan = scans.scan(session, scan_id)
    if scan is None:
        raise Problem(404, "not-found", f"There is no scan {scan_id!r}.")
    return scan


ExistingScan = Annotated[Scan, Depends(_existing_scan)]


def scan_out(scan: Scan, job: Job) -> ScanOut:
    return ScanOut(scan_id=scan.id, station=scan.station, part_id=scan.part_id,
                   calibration_set_id=scan.calibration_set_id, part_type_id=scan.part_type_id, job_id=scan.job_id,
                   status=job.status, created_at=scan.created_at, summary=scan.summary, verdict=scan.verdict,
                   features=scan.features, links=scan_links(scan))


@router.post("", name="create_scan", status_code=202, response_model=Accepted,
             responses={202: {"headers": {"Location": {"description": "The scan's job."}}}, **problem_responses(409)})
async def create_scan(request: Request, session: SessionDep, runtime: RuntimeDep, queue: JobQueueDep,
                      key: OperatorKey, idempotency_key: IdempotencyKeyHeader = None, body: ScanRequest | None = None):
    """Scan the part in the station: capture, reconstruct, fuse, inspect (against the part type named or the
    station's selected one), store and stream, as a background job."""
    body = body or ScanRequest()
    station = runtime.settings.station

    def start() -> Outcome:
        try:
            inputs = scan_inputs(session, station, calibration_set_id=body.calibration_set_id,
                                 part_type_id=body.part_type_id)
        except JobRefused as refused:
            raise refused_problem(refused) from None
        scan = new_scan(station, inputs, part_id=body.part_id)
        return start_job(runtime, queue, session, "scan", scan_job_params(scan.id, inputs), scan)

    digest = request_digest(request, await request.body())
    return await run_in_threadpool(respond_once, session, key, idempotency_key, digest, start,
                                   runtime.settings.idempotency_ttl_s)


@router.post("/{scan_id}/jobs", name="create_scan_job", status_code=202, response_model=Accepted,
             responses={202: {"headers": {"Location": {"description": "The job."}}}, **problem_responses(404, 409)})
async def create_scan_job(request: Request, key: OperatorKey, scan: ExistingScan, body: ScanJobRequest,
                          session: SessionDep, runtime: RuntimeDep, queue: JobQueueDep,
                          idempotency_key: IdempotencyKeyHeader = None):
    """Run one step again on a stored scan: reconstruct or fuse (e.g. with another calibration set), or register
    its thermal frame onto its camera frame by mutual information. Results: ``/v1/jobs/{id}/artifacts/{name}``."""
    digest = request_digest(request, await request.body())

    def start() -> Outcome:
        try:
            params = stored_scan_job_params(session, scan, kind=body.kind, calibration_set_id=body.calibration_set_id,
                                            model=body.model, cloud_job_id=body.cloud_job_id)
        except JobRefused as refused:
            raise refused_problem(refused) from None
        return start_job(runtime, queue, session, body.kind, params)

    return await run_in_threadpool(respond_once, session, key, idempotency_key, digest, start,
                                   runtime.settings.idempotency_ttl_s)


@router.get("", name="list_scans")
def list_scans(session: SessionDep, runtime: RuntimeDep, _: ReaderKey,
               limit: Annotated[int, Query(ge=1, le=1000, description="At most this many scans.")] = 100,
               part_id: Annotated[str | None, Query(max_length=200, description="Only the scans of this part "
                                                                                "(the MES's identifier).")] = None,
               part_type_id: Annotated[str | None, Query(max_length=64, description="Only the scans inspected "
                                                                                    "against this part type.")] = None,
               ) -> list[ScanOut]:
    """The station's most recent scans, newest first, optionally only those of one part or part type."""
    rows = scans.station_scans(session, runtime.settings.station, limit=limit, part_id=part_id,
                               part_type_id=part_type_id)
    return [scan_out(scan, job) for scan, job in rows]


@router.get("/{scan_id}", name="get_scan", responses=problem_responses(404))
def get_scan(scan: ExistingScan, session: SessionDep) -> ScanOut:
    """Metadata, links to the artifacts, the field's summary (point count, bounding box, temperatures) and,
    when inspected, the verdict and the features."""
    return scan_out(scan, scans.scan_job(session, scan))


@router.get("/{scan_id}/{artifact}", name="download_scan_artifact",
            responses={200: {"content": {"application/octet-stream": {}}}, **problem_responses(404)})
def download_scan_artifact(scan: ExistingScan, runtime: RuntimeDep, session: SessionDep,
                           artifact: Annotated[str, Path(pattern=ARTIFACT_NAME_PATTERN)]):
    """The point cloud (``cloud.ply``), the temperature field (``field.ply``), its Rerun recording
    (``field.rrd``), all raw frames as one NumPy array (``frames.npy`` uint8/uint16, ``thermal.npy``
    float32 degrees C) or, when inspected, the report (``report.json``) and the cold-equivalent cloud with
    the per-point ``deviation`` (``deviation.ply``)."""
    digest = scan.artifacts.get(artifact)
    if digest is None:
        _never_or_not_yet(scan, scans.scan_job(session, scan), artifact)
    return _artifact_file(runtime, scan, digest, f"{scan.id}-{artifact}", SERVED[artifact].media_type)


def _never_or_not_yet(scan: Scan, job: Job, artifact: str) -> None:
    """A 404 that says whether the artifact may still come: ``not-ready`` while the scan's job runs, else
    ``not-found`` with the reason it never will (no part type to inspect against, or the job's end)."""
    if SERVED[artifact].inspected and scan.part_type_id is None:
        raise Problem(404, "not-found", f"Scan {scan.id} has no {artifact} and will have none: it was not "
                                        "inspected (no part type was named or selected when it started).")
    if job.status in TERMINAL_STATUSES:
        raise Problem(404, "not-found", f"Scan {scan.id} has no {artifact} and will have none: its job "
                                        f"{job.id} has {job.status}.")
    raise Problem(404, "not-ready", f"Scan {scan.id} has no {artifact} yet; its job {job.id} is {job.status}.")


@router.get("/{scan_id}/{kind}/{index}.{suffix}", name="download_scan_frame",
            responses={200: {"content": {"image/png": {}, "image/tiff": {}}}, **problem_responses(404)})
def download_scan_frame(scan: ExistingScan, runtime: RuntimeDep,
                        kind: Annotated[str, Path(pattern="^(frames|thermal)$")], index: int,
                        suffix: Annotated[str, Path(pattern="^(png|tiff)$")]) -> Response:
    """One raw frame of the capture: camera ``frames/<i>.png`` or thermal ``thermal/<i>.tiff`` (float32 °C)."""
    stack, media_type, expected_suffix = FRAME_KINDS[kind]
    digest = scan.artifacts.get(stack.name)
    if digest is None:
        raise Problem(404, "not-ready", f"Scan {scan.id} has no {kind} (yet); see its job.")
    frames = np.load(stored_path(runtime.store, digest, f"scan {scan.id}"), mmap_mode="r", allow_pickle=False)
    if suffix != expected_suffix or not 0 <= index < len(frames):
        raise Problem(404, "not-found", f"Scan {scan.id} has no {kind}/{index}.{suffix} "
                                        f"({len(frames)} {kind}, numbered from 0, as .{expected_suffix}).")
    return Response(encode_frame(np.asarray(frames[index]), expected_suffix), media_type=media_type)


def _artifact_file(runtime, scan: Scan, digest: str | None, filename: str, media_type: str) -> FileResponse:
    if digest is None:
        raise Problem(404, "not-ready", f"Scan {scan.id} does not have this artifact (yet); see its job.")
    return FileResponse(stored_path(runtime.store, digest, f"scan {scan.id}"), media_type=media_type,
                        filename=filename)
