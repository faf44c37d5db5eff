"""Calibration sets: upload a rig file; list, get, download as a rig file, activate one per station."""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Depends, File, Form, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response
from sqlalchemy import select, update

from api.deps import AdminKey, ReaderKey, RuntimeDep, SessionDep
from api.idempotency import IdempotencyKeyHeader, Outcome, request_digest, respond_once
from api.problems import Problem
from api.schemas import CalibrationSetOut
from services.db.models import CalibrationSet
from services.formats.rig import parse_rig, rig_to_json

router = APIRouter(prefix="/calibration-sets", tags=["calibration"])
_MAX_RIG_BYTES = 1 << 20


def calibration_out(calibration: CalibrationSet) -> CalibrationSetOut:
    links = {"self": f"/v1/calibration-sets/{calibration.id}"}
    if calibration.rig_sha256:
        links["rig"] = f"/v1/calibration-sets/{calibration.id}/rig.json"
    return CalibrationSetOut(calibration_set_id=calibration.id, name=calibration.name, station=calibration.station,
                             active=calibration.active, source=calibration.source,
                             created_at=calibration.created_at, links=links)


def _existing_calibration(calibration_set_id: str, session: SessionDep, _: ReaderKey) -> CalibrationSet:
    calibration = session.get(CalibrationSet, calibration_set_id)
    if calibration is None:
        raise Problem(404, "not-found", f"There is no calibration set {calibration_set_id!r}.")
    return calibration


ExistingCalibration = Annotated[CalibrationSet, Depends(_existing_calibration)]


@router.post("", name="create_calibration_set", status_code=201, response_model=CalibrationSetOut)
async def create_calibration_set(request: Request, session: SessionDep, runtime: RuntimeDep, key: AdminKey,
                                 rig: Annotated[UploadFile, File(description="A rig file (docs/rig-file.md).")],
                                 name: Annotated[str, Form(min_length=1, max_length=200)],
                                 activate: Annotated[bool, Form()] = False,
                                 idempotency_key: IdempotencyKeyHeader = None):
    """Store an uploaded, validated rig file as a calibration set of this station."""
    text = (await rig.read(_MAX_RIG_BYTES + 1))
    if len(text) > _MAX_RIG_BYTES:
        raise Problem(413, "too-large", f"rig: the file {rig.filename!r} is larger than {_MAX_RIG_BYTES} bytes.")
    parsed = parse_rig(text.decode("utf-8", errors="replace"), f"rig ({rig.filename})")
    rig_digest = runtime.store.put_bytes(rig_to_json(parsed).encode())

    def create() -> Outcome:
        calibration = CalibrationSet(name=name, station=runtime.settings.station, rig_sha256=rig_digest,
                                     source="upload")
        session.add(calibration)
        session.flush()
        if activate:
            _activate(session, calibration)
        out = calibration_out(calibration)
        return Outcome(201, out.model_dump(mode="json"), out.links["self"])

    request_sha256 = request_digest(request, json.dumps({"name": name, "activate": activate}).encode() + text)
    return await run_in_threadpool(respond_once, session, key, idempotency_key, request_sha256, create)


@router.get("", name="list_calibration_sets")
def list_calibration_sets(session: SessionDep, runtime: RuntimeDep, _: ReaderKey) -> list[CalibrationSetOut]:
    """This station's calibration sets, newest first."""
    rows = session.scalars(select(CalibrationSet).where(CalibrationSet.station == runtime.settings.station)
                           .order_by(CalibrationSet.created_at.desc()))
    return [calibration_out(calibration) for calibration in rows]


@router.get("/{calibration_set_id}", name="get_calibration_set")
def get_calibration_set(calibration: ExistingCalibration) -> CalibrationSetOut:
    return calibration_out(calibration)


@router.get("/{calibration_set_id}/rig.json", name="download_calibration_set",
            responses={200: {"content": {"application/json": {}}}})
def download_calibration_set(calibration: ExistingCalibration, runtime: RuntimeDep) -> Response:
    """The calibration set as a rig file."""
    if calibration.rig_sha256 is None:
        raise Problem(404, "not-ready", f"Calibration set {calibration.id} has no rig yet.")
    return Response(runtime.store.read_bytes(calibration.rig_sha256), media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{calibration.id}-rig.json"'})


@router.post("/{calibration_set_id}/activate", name="activate_calibration_set")
def activate_calibration_set(calibration: ExistingCalibration, session: SessionDep, _: AdminKey) -> CalibrationSetOut:
    """Make this the station's active calibration set (new scans use it)."""
    if calibration.rig_sha256 is None:
        raise Problem(409, "not-ready", f"Calibration set {calibration.id} has no rig yet and cannot be active.")
    _activate(session, calibration)
    session.commit()
    return calibration_out(calibration)


def _activate(session, calibration: CalibrationSet) -> None:
    session.execute(update(CalibrationSet).where(CalibrationSet.station == calibration.station,
                                                 CalibrationSet.id != calibration.id).values(active=False))
    calibration.active = True
