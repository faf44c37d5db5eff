"""Retention: which scans keep their artifacts, expiring idempotency records, and sweeping unreferenced blobs.

A scan takes about 100 MB (mostly its raw frames). Per station, a scan keeps its
fields (cloud, field, recording) while it is among the newest ``keep_scans`` **or**
younger than ``keep_days``; its raw frames (``frames.npy``, ``thermal.npy``,
``sequence.json``; a station scan's per head and per thermal camera,
:func:`services.formats.stored_scan.is_raw`) go after ``raw_frames_days``
already. Expiry removes the digests from the scan's and its jobs' rows (the
rows, summary and history stay; a station head's job loses its frames' digests
from its parameters);
the blobs themselves are removed by a mark-and-sweep of the store: every blob
that no row references and that is older than a grace period (so that a blob a
running job has just written, before its row names it, survives) is deleted.
:func:`run_maintenance` does all of it; the service runs it periodically
(``THERMOFIELD_MAINTENANCE_INTERVAL_S``), ``thermofield maintenance`` once.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

from sqlalchemy import delete, select
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import CalibrationSet, IdempotencyRecord, Job, PartType, Scan
from services.formats.stored_scan import is_raw
from services.storage.artifacts import ArtifactStore

logger = logging.getLogger(__name__)
_DIGEST = re.compile(r"^[0-9a-f]{64}$")


@dataclass(frozen=True)
class RetentionPolicy:
    """What to keep; 0 days or scans means that criterion keeps nothing by itself."""

    keep_scans: int = 100
    keep_days: float = 7.0
    raw_frames_days: float = 1.0
    idempotency_ttl_s: float = 86400.0
    blob_grace_s: float = 3600.0


@dataclass
class MaintenanceReport:
    scans_expired: int = 0
    raw_frames_expired: int = 0
    idempotency_records_deleted: int = 0
    blobs_deleted: int = 0
    bytes_freed: int = 0


def _aware(moment: datetime) -> datetime:
    return moment if moment.tzinfo else moment.replace(tzinfo=UTC)  # SQLite returns naive UTC


def _without(artifacts: dict[str, Any], raw_only: bool) -> dict[str, Any]:
    """``artifacts`` without the raw ones (``raw_only``) or without any."""
    return {name: digest for name, digest in artifacts.items() if raw_only and not is_raw(name)}


def expire_scans(session: Session, policy: RetentionPolicy, now: datetime) -> tuple[int, int]:
    """Drop the artifact digests of scans past the policy from their rows (the caller commits).

    Returns
    -------
    scans_expired, raw_frames_expired : int
        Scans that lost all their artifacts, and scans that lost only their raw frames.
    """
    scans = list(session.scalars(select(Scan).order_by(Scan.station, Scan.created_at.desc())))
    jobs_by_scan: dict[str, list[Job]] = {}
    for job in session.scalars(select(Job)):
        scan_id = job.params.get("scan_id")
        if scan_id is not None:
            jobs_by_scan.setdefault(scan_id, []).append(job)
    rank: dict[str, int] = {}
    expired = raw_only = 0
    for scan in scans:
        rank[scan.station] = rank.get(scan.station, 0) + 1
        if not scan.artifacts:
            continue
        age = now - _aware(scan.created_at)
        keeps_fields = rank[scan.station] <= policy.keep_scans or age < timedelta(days=policy.keep_days)
        keeps_raw = keeps_fields and age < timedelta(days=policy.raw_frames_days)
        if keeps_raw:
            continue
        if keeps_fields and not any(is_raw(name) for name in scan.artifacts):
            continue
        scan.artifacts = _without(scan.artifacts, raw_only=keeps_fields)
        for job in jobs_by_scan.get(scan.id, []):
            if job.result.get("artifacts"):
                job.result = {**job.result, "artifacts": _without(job.result["artifacts"], raw_only=keeps_fields)}
            if any(is_raw(name) for name in job.params):  # a station head's job names its frames
                job.params = {name: value for name, value in job.params.items() if not is_raw(name)}
        if keeps_fields:
            raw_only += 1
        else:
            expired += 1
    return expired, raw_only


def expire_idempotency_records(session: Session, ttl_s: float, now: datetime) -> int:
    """Delete the idempotency records older than ``ttl_s`` (the caller commits)."""
    result = session.execute(delete(IdempotencyRecord).where(IdempotencyRecord.created_at < now - timedelta(seconds=ttl_s)))
    return result.rowcount or 0


def _digests(value: Any) -> Iterator[str]:
    if isinstance(value, str):
        if _DIGEST.match(value):
            yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from _digests(item)
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _digests(item)


def referenced_digests(session: Session) -> set[str]:
    """Every blob digest a row names: scan artifacts, job params and results, calibration rigs."""
    referenced = set(_digests([scan.artifacts for scan in session.scalars(select(Scan))]))
    for params, result in session.execute(select(Job.params, Job.result)):
        referenced.update(_digests(params))
        referenced.update(_digests(result))
    referenced.update(digest for digest in session.scalars(select(CalibrationSet.rig_sha256)) if digest)
    for part_sha256, mesh_sha256 in session.execute(select(PartType.part_sha256, PartType.mesh_sha256)):
        referenced.update((part_sha256, mesh_sha256))  # part types keep their files whatever their age
    return referenced


def sweep_store(store: ArtifactStore, referenced: set[str], grace_s: float) -> tuple[int, int]:
    """Delete the blobs not in ``referenced`` whose file is older than ``grace_s``; (count, bytes)."""
    count = freed = 0
    cutoff = time.time() - grace_s
    for digest, path in store.blobs():
        if digest in referenced:
            continue
        stat = path.stat()
        if stat.st_mtime >= cutoff:
            continue
        path.unlink(missing_ok=True)
        count, freed = count + 1, freed + stat.st_size
    return count, freed


def run_maintenance(sessions: sessionmaker[Session], store: ArtifactStore, policy: RetentionPolicy,
                    now: datetime | None = None) -> MaintenanceReport:
    """Apply the retention policy, expire idempotency records and sweep the store, in that order."""
    now = now or datetime.now(UTC)
    report = MaintenanceReport()
    with sessions.begin() as session:
        report.scans_expired, report.raw_frames_expired = expire_scans(session, policy, now)
        report.idempotency_records_deleted = expire_idempotency_records(session, policy.idempotency_ttl_s, now)
    with sessions() as session:
        referenced = referenced_digests(session)
    report.blobs_deleted, report.bytes_freed = sweep_store(store, referenced, policy.blob_grace_s)
    return report


class MaintenanceThread:
    """Runs :func:`run_maintenance` every ``interval_s`` in a daemon thread (first run after one interval)."""

    def __init__(self, sessions: sessionmaker[Session], store: ArtifactStore, policy: RetentionPolicy,
                 interval_s: float) -> None:
        self.sessions, self.store, self.policy, self.interval_s = sessions, store, policy, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="thermofield-maintenance", daemon=True)

    def __enter__(self) -> MaintenanceThread:
        if self.interval_s > 0:
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                report = run_maintenance(self.sessions, self.store, self.policy)
                logger.info("Maintenance: %s", report)
            except Exception:  # a database outage must not end the thread; the next run retries
                logger.exception("Maintenance failed; retrying in %.0f s", self.interval_s)

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
