"""Database tables of the service (not the API schemas: those live in ``api/schemas.py``).

Large data (frames, clouds, fields, recordings) never enters the database: rows hold
the SHA-256 digests of artifacts in the content-addressed store (``services/storage``).
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Integer, String, Text, TypeDecorator, UniqueConstraint
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column

JOB_STATUSES = ("queued", "running", "succeeded", "failed")
TERMINAL_STATUSES = ("succeeded", "failed")


def utc_now() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return uuid.uuid4().hex


class UtcDateTime(TypeDecorator):
    """A timezone-aware timestamp on every database: SQLite keeps no time zone and returns naive values,
    which are UTC here (every timestamp is written by :func:`utc_now`)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        if value is not None and value.tzinfo is None:
            return value.replace(tzinfo=UTC)
        return value


class Base(DeclarativeBase):
    type_annotation_map = {datetime: UtcDateTime(), dict[str, Any]: JSON}


class ApiKey(Base):
    """An API key: only the SHA-256 of the secret is kept, with its scopes."""

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    secret_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    scopes: Mapped[str] = mapped_column(String(100), doc="Space-separated subset of read, operate, admin.")
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    revoked_at: Mapped[datetime | None] = mapped_column(default=None)


class CalibrationSet(Base):
    """A calibrated rig (the rig JSON is an artifact); at most one is active per station."""

    __tablename__ = "calibration_sets"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200))
    station: Mapped[str] = mapped_column(String(100), index=True)
    rig_sha256: Mapped[str | None] = mapped_column(String(64), default=None)
    active: Mapped[bool] = mapped_column(Boolean, default=False)
    source: Mapped[str] = mapped_column(String(20), doc="upload, calibration or simulator.")
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class PartType(Base):
    """A part type (the recipe of OPC 40100-1): a part file and its nominal mesh (artifacts); at most one is
    selected per station, which scans inspect against unless they name another."""

    __tablename__ = "part_types"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(200), doc="The part file's name.")
    station: Mapped[str] = mapped_column(String(100), index=True)
    material: Mapped[str] = mapped_column(String(200), doc="Built-in material name, or a custom table's name.")
    part_sha256: Mapped[str] = mapped_column(String(64), doc="The part file as uploaded.")
    mesh_sha256: Mapped[str] = mapped_column(String(64), doc="The nominal mesh as uploaded.")
    selected: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class Job(Base):
    """One unit of background work; the source of truth for its status and progress."""

    __tablename__ = "jobs"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    kind: Mapped[str] = mapped_column(String(30), doc="calibrate, reconstruct, register, fuse, scan, scan_head or ...")
    status: Mapped[str] = mapped_column(String(20), default="queued", index=True)
    stage: Mapped[str] = mapped_column(String(50), default="queued")
    fraction: Mapped[float] = mapped_column(Float, default=0.0)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(200), default=None, doc="host:pid that ran the last attempt.")
    error: Mapped[str | None] = mapped_column(Text, default=None)
    params: Mapped[dict[str, Any]] = mapped_column(default=dict)
    result: Mapped[dict[str, Any]] = mapped_column(default=dict, doc="Artifact digests and other outputs.")
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
    started_at: Mapped[datetime | None] = mapped_column(default=None)
    finished_at: Mapped[datetime | None] = mapped_column(default=None)
    dispatched_at: Mapped[datetime | None] = mapped_column(
        default=None, index=True, doc="When its message reached the broker; None while it waits in the outbox.")
    heartbeat_at: Mapped[datetime | None] = mapped_column(
        default=None, doc="Renewed every few seconds by the worker running it: its lease on the job.")
    updated_at: Mapped[datetime] = mapped_column(default=utc_now, onupdate=utc_now)


class Scan(Base):
    """A scanned part: its job, the calibration used, artifact digests, the field summary and, when it was
    inspected, its part type, verdict and features (the report is an artifact)."""

    __tablename__ = "scans"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    station: Mapped[str] = mapped_column(String(100), index=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id"))
    calibration_set_id: Mapped[str] = mapped_column(ForeignKey("calibration_sets.id"))
    part_id: Mapped[str | None] = mapped_column(String(200), default=None)
    part_type_id: Mapped[str | None] = mapped_column(ForeignKey("part_types.id"), default=None,
                                                     doc="The part type the scan is inspected against.")
    verdict: Mapped[str | None] = mapped_column(String(20), default=None, doc="OK, NotOK or NotDecidable.")
    features: Mapped[list[Any] | None] = mapped_column(JSON, default=None, doc="The report's features.")
    artifacts: Mapped[dict[str, Any]] = mapped_column(default=dict, doc="Artifact name -> SHA-256 digest.")
    summary: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)


class GroupBarrier(Base):
    """A Dramatiq group's completion barrier (``services.jobs.barrier``): the parties it still waits for."""

    __tablename__ = "group_barriers"

    key: Mapped[str] = mapped_column(String(100), primary_key=True)
    value: Mapped[int] = mapped_column(Integer)
    expires_at: Mapped[datetime] = mapped_column(index=True)


class IdempotencyRecord(Base):
    """The first response to a POST carrying an ``Idempotency-Key``, replayed on retries."""

    __tablename__ = "idempotency_records"
    __table_args__ = (UniqueConstraint("api_key_id", "key"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    api_key_id: Mapped[str] = mapped_column(ForeignKey("api_keys.id"))
    key: Mapped[str] = mapped_column(String(255))
    request_sha256: Mapped[str] = mapped_column(String(64), doc="Method, path and body of the first request.")
    status_code: Mapped[int] = mapped_column(Integer)
    location: Mapped[str | None] = mapped_column(String(500), default=None)
    body: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(default=utc_now)
