"""Starting a scan, as the HTTP API and the OPC UA server both do: its calibration set and part type checked,
the bound on waiting jobs kept, its scan and job rows added (the caller commits, then announces the job and
sends it to the ``scan`` actor by name through the outbox). Starting a job on a stored scan (``reconstruct``,
``fuse``, ``register``): its inputs checked, its parameters made."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from services.db.models import CalibrationSet, Job, PartType, Scan, new_id
from services.db.parts import selected_part_type
from services.errors import InputError
from services.formats.stored_scan import CLOUD, FRAMES
from services.jobs.tracker import JobTracker


class JobRefused(InputError):
    """A job the station cannot take; ``kind`` says why: ``invalid-input`` (a calibration set or part type that
    is not the station's), ``no-active-calibration``, ``not-ready`` (a scan without its capture yet) or
    ``queue-full``."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def check_queue_bound(session: Session, bound: int) -> None:
    """Refuse a new job when ``bound`` jobs (``THERMOFIELD_JOB_QUEUE_BOUND``, 0: none) already wait."""
    if bound and session.scalar(select(func.count()).select_from(Job).where(Job.status == "queued")) >= bound:
        raise JobRefused("queue-full", f"{bound} jobs are already waiting, the most the station queues; "
                                       "retry later.")


@dataclass(frozen=True)
class ScanInputs:
    """What a new scan of a station uses: its calibration set and the part type it is inspected against."""

    calibration: CalibrationSet
    part_type: PartType | None


def scan_inputs(session: Session, station: str, *, calibration_set_id: str | None = None,
                part_type_id: str | None = None) -> ScanInputs:
    """The calibration set (the named one, else the station's active one) and part type (the named one, else the
    station's selected one, else none) of a new scan of ``station``."""
    if calibration_set_id is not None:
        calibration = session.get(CalibrationSet, calibration_set_id)
        if calibration is None or calibration.station != station:
            raise JobRefused("invalid-input", f"calibration_set_id: there is no calibration set "
                                              f"{calibration_set_id!r} for station {station!r}.")
    else:
        calibration = session.scalar(
            select(CalibrationSet).where(CalibrationSet.station == station, CalibrationSet.active.is_(True)))
        if calibration is None:
            raise JobRefused("no-active-calibration", f"Station {station!r} has no active calibration set; "
                                                      "activate one or pass calibration_set_id.")
    if part_type_id is None:
        return ScanInputs(calibration, selected_part_type(session, station))
    part_type = session.get(PartType, part_type_id)
    if part_type is None or part_type.station != station:
        raise JobRefused("invalid-input", f"part_type_id: there is no part type {part_type_id!r} for station "
                                          f"{station!r} (see GET /v1/part-types).")
    return ScanInputs(calibration, part_type)


def scan_job_params(scan_id: str, inputs: ScanInputs, **extra: Any) -> dict[str, Any]:
    """The ``scan`` actor's parameters; ``extra`` keys (e.g. the OPC UA client's MeasId) ride along unread."""
    return {"scan_id": scan_id, "calibration_set_id": inputs.calibration.id,
            "part_type_id": None if inputs.part_type is None else inputs.part_type.id, **extra}


def new_scan(station: str, inputs: ScanInputs, *, part_id: str | None = None) -> Scan:
    """A scan row of ``station`` with its inputs (not yet added: its job adds it)."""
    return Scan(id=new_id(), station=station, calibration_set_id=inputs.calibration.id, part_id=part_id,
                part_type_id=None if inputs.part_type is None else inputs.part_type.id)


def add_scan_job(session: Session, tracker: JobTracker, station: str, inputs: ScanInputs, *,
                 part_id: str | None = None, bound: int = 0, **extra: Any) -> tuple[Job, Scan]:
    """Add a queued scan job and its scan to ``session`` (the caller commits, then announces the job and sends
    it); :class:`JobRefused` when ``bound`` jobs already wait."""
    check_queue_bound(session, bound)
    scan = new_scan(station, inputs, part_id=part_id)
    job = tracker.create(session, "scan", scan_job_params(scan.id, inputs, **extra))
    scan.job_id = job.id
    session.add(scan)
    return job, scan


def stored_scan_job_params(session: Session, scan: Scan, *, kind: str, calibration_set_id: str | None = None,
                           model: str | None = None, cloud_job_id: str | None = None) -> dict[str, Any]:
    """The parameters of a ``kind`` job (``reconstruct``, ``fuse``, ``register``) on the stored ``scan``: with
    the named calibration set of the scan's station (default the scan's own), the ``register`` job's ``model``,
    the ``fuse`` job's cloud of a succeeded reconstruct job of this scan. :class:`JobRefused` when the scan has
    no stored capture yet (``not-ready``) or an input is not the scan's (``invalid-input``)."""
    if scan.artifacts.get(FRAMES.name) is None:
        raise JobRefused("not-ready", f"Scan {scan.id} has no stored capture yet; wait for its job.")
    params: dict[str, Any] = {"scan_id": scan.id, "calibration_set_id": scan.calibration_set_id}
    if calibration_set_id is not None:
        params["calibration_set_id"] = scan_inputs(session, scan.station,
                                                   calibration_set_id=calibration_set_id).calibration.id
    if kind == "register":
        params["model"] = model
    if cloud_job_id is not None:
        cloud_job = session.get(Job, cloud_job_id)
        if kind != "fuse" or cloud_job is None or cloud_job.kind != "reconstruct" \
                or cloud_job.params.get("scan_id") != scan.id or cloud_job.status != "succeeded":
            raise JobRefused("invalid-input", f"cloud_job_id: {cloud_job_id!r} is not a succeeded reconstruct job "
                                              f"of scan {scan.id} (and only a fuse job takes one).")
        params["cloud_sha256"] = cloud_job.result["artifacts"][CLOUD.name]
    return params
