"""The station as the OPC UA server reads and changes it, through the service's database (so that it sees every
worker's jobs, scaled out or embedded): recipes are part types, configurations are calibration sets, results
are scans. Blocking functions, called from the server's loop in a thread."""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session, sessionmaker

from services.db.calibrations import activate_calibration
from services.db.models import CalibrationSet, Job, PartType, Scan
from services.db.parts import select_part_type
from services.jobs.outbox import Outbox
from services.jobs.scans import add_scan_job, scan_inputs
from services.jobs.tracker import JobTracker, job_state

ABORTED = "aborted by the OPC UA client"
"""The error of a queued job the client's Abort cancelled (its result's state is Aborted)."""

RESULT_SCAN_LIMIT = 10_000
"""Most recent scans a result filter looks through."""


@dataclass(frozen=True)
class Recipe:
    """A part type of the station: ``internal_id`` its id, ``external_id`` (and product) its name."""

    internal_id: str
    external_id: str
    material: str
    prepared: bool


@dataclass(frozen=True)
class Configuration:
    """A calibration set of the station: ``internal_id`` its id, ``external_id`` its name."""

    internal_id: str
    external_id: str
    active: bool
    has_rig: bool
    created_at: datetime


@dataclass(frozen=True)
class Result:
    """A scan and its job: the OPC UA result ``result_id`` (the scan's id) of job ``job_id`` (the OPC UA job:
    a continuous run's id, else the scan job's)."""

    result_id: str
    job_id: str
    scan_job_id: str
    status: str
    error: str | None
    meas_id: str
    part_id: str
    recipe: Recipe | None
    configuration_id: str
    configuration_name: str
    verdict: str | None
    features: list[Any] | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    stage_seconds: dict[str, float] = field(default_factory=dict)

    @property
    def finished(self) -> bool:
        return self.status in ("succeeded", "failed")


@dataclass(frozen=True)
class ResultFilter:
    """GetResultListFiltered's filters; None passes everything."""

    result_state: int | None = None
    meas_id: str | None = None
    part_id: str | None = None
    recipe_external_id: str | None = None
    recipe_internal_id: str | None = None
    configuration_external_id: str | None = None
    configuration_internal_id: str | None = None
    product_id: str | None = None
    job_id: str | None = None


def result_state(result: Result) -> int:
    """ResultStateDataType (OPC 40100-1, 12.19): 1 Completed, 2 Processing, 3 Aborted, 4 Failed."""
    if result.status == "succeeded":
        return 1
    if result.status == "failed":
        return 3 if result.error == ABORTED else 4
    return 2


class Station:
    """One station's recipes, configurations, results and scans in the database at ``sessions``; new scans go to
    ``tracker`` (rows, announcements) and ``outbox`` (the ``scan`` actor's messages)."""

    def __init__(self, sessions: sessionmaker[Session], station: str, tracker: JobTracker,
                 outbox: Outbox | None, queue_bound: int = 0) -> None:
        self.sessions, self.name, self.tracker, self.outbox = sessions, station, tracker, outbox
        self.queue_bound = queue_bound

    # recipes (part types)

    def recipes(self) -> list[Recipe]:
        with self.sessions() as session:
            rows = session.scalars(select(PartType).where(PartType.station == self.name)
                                   .order_by(PartType.created_at, PartType.id))
            return [_recipe(row) for row in rows]

    def find_recipe(self, internal_id: str | None, external_id: str | None) -> Recipe | None:
        """The recipe named by its internal id (which takes precedence) or its external id (the part type's
        name; the newest of that name)."""
        recipes = self.recipes()
        if internal_id:
            return next((recipe for recipe in recipes if recipe.internal_id == internal_id), None)
        named = [recipe for recipe in recipes if recipe.external_id == external_id] if external_id else []
        return named[-1] if named else None

    def prepare(self, recipe: Recipe) -> None:
        """Select the part type: scans that name none are inspected against it (the one prepared recipe)."""
        with self.sessions.begin() as session:
            select_part_type(session, session.get(PartType, recipe.internal_id))

    def unprepare(self, recipe: Recipe) -> None:
        with self.sessions.begin() as session:
            session.execute(update(PartType).where(PartType.id == recipe.internal_id).values(selected=False))

    # configurations (calibration sets)

    def configurations(self) -> list[Configuration]:
        with self.sessions() as session:
            rows = session.scalars(select(CalibrationSet).where(CalibrationSet.station == self.name)
                                   .order_by(CalibrationSet.created_at, CalibrationSet.id))
            return [_configuration(row) for row in rows]

    def find_configuration(self, internal_id: str | None) -> Configuration | None:
        return next((c for c in self.configurations() if internal_id and c.internal_id == internal_id), None)

    def activate(self, configuration: Configuration) -> None:
        with self.sessions.begin() as session:
            activate_calibration(session, session.get(CalibrationSet, configuration.internal_id))

    # results (scans)

    def result(self, scan_id: str) -> Result | None:
        with self.sessions() as session:
            scan = session.get(Scan, scan_id)
            if scan is None or scan.station != self.name:
                return None
            return _result(session, scan, session.get(Job, scan.job_id))

    def results(self, where: ResultFilter) -> list[Result]:
        """The station's results that pass ``where``, newest first."""
        with self.sessions() as session:
            query = (select(Scan, Job).join(Job, Scan.job_id == Job.id).where(Scan.station == self.name)
                     .order_by(Scan.created_at.desc(), Scan.id.desc()).limit(RESULT_SCAN_LIMIT))
            if where.part_id is not None:
                query = query.where(Scan.part_id == where.part_id)
            if where.recipe_internal_id is not None:
                query = query.where(Scan.part_type_id == where.recipe_internal_id)
            if where.configuration_internal_id is not None:
                query = query.where(Scan.calibration_set_id == where.configuration_internal_id)
            rows = [_result(session, scan, job) for scan, job in session.execute(query)]
        return [result for result in rows if _passes(result, where)]

    def in_flight(self) -> list[dict[str, Any]]:
        """The job states of the scan jobs waiting or running (what the server follows after it starts)."""
        with self.sessions() as session:
            jobs = session.scalars(select(Job).join(Scan, Scan.job_id == Job.id).where(
                Scan.station == self.name, Job.kind == "scan", Job.status.in_(("queued", "running"))))
            return [job_state(job) for job in jobs]

    # jobs

    def start_scan(self, *, part_id: str | None, recipe: Recipe | None, meas_id: str, job_id: str | None) -> Job:
        """Queue a scan job of the station with its active calibration set and ``recipe`` (else the prepared
        one), then announce and send it. ``job_id`` is the OPC UA job it belongs to (a continuous run), kept with
        the client's ``meas_id`` in the job's parameters. :class:`~services.jobs.scans.JobRefused` when it
        cannot be."""
        extra = {key: value for key, value in (("meas_id", meas_id), ("opcua_job_id", job_id)) if value}
        with self.sessions.begin() as session:
            inputs = scan_inputs(session, self.name, part_type_id=None if recipe is None else recipe.internal_id)
            job, _ = add_scan_job(session, self.tracker, self.name, inputs, part_id=part_id, bound=self.queue_bound,
                                  **extra)
        self.tracker.announce(job)
        if self.outbox is not None:
            self.outbox.send(job.id)  # False: it waits in the outbox, whose thread in the API process sends it
        return job

    def abort_queued(self, job_ids: set[str]) -> list[str]:
        """Fail those of ``job_ids`` that no worker has started (a worker skips a finished job's message)."""
        with self.sessions() as session:
            queued = list(session.scalars(select(Job.id).where(Job.id.in_(job_ids), Job.status == "queued")))
        for job_id in queued:
            self.tracker.fail(job_id, ABORTED, will_retry=False)
        return queued


def _recipe(row: PartType) -> Recipe:
    return Recipe(row.id, row.name, row.material, bool(row.selected))


def _configuration(row: CalibrationSet) -> Configuration:
    return Configuration(row.id, row.name, bool(row.active), row.rig_sha256 is not None, row.created_at)


def _result(session: Session, scan: Scan, job: Job) -> Result:
    part_type = session.get(PartType, scan.part_type_id) if scan.part_type_id else None
    calibration = session.get(CalibrationSet, scan.calibration_set_id)
    params, outputs = job.params or {}, job.result or {}
    return Result(
        result_id=scan.id, job_id=params.get("opcua_job_id") or job.id, scan_job_id=job.id, status=job.status,
        error=job.error, meas_id=params.get("meas_id") or "", part_id=scan.part_id or "",
        recipe=None if part_type is None else _recipe(part_type), configuration_id=scan.calibration_set_id,
        configuration_name=calibration.name if calibration else "", verdict=scan.verdict, features=scan.features,
        created_at=scan.created_at, started_at=job.started_at, finished_at=job.finished_at,
        stage_seconds=dict(outputs.get("stage_seconds") or {}))


def _passes(result: Result, where: ResultFilter) -> bool:
    recipe_name = "" if result.recipe is None else result.recipe.external_id
    checks = ((where.result_state, result_state(result)), (where.meas_id, result.meas_id),
              (where.recipe_external_id, recipe_name), (where.product_id, recipe_name),
              (where.configuration_external_id, result.configuration_name), (where.job_id, result.job_id))
    return all(wanted is None or wanted == value for wanted, value in checks)
