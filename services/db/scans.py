"""Scans' rows: one scan and its job, a station's scans, and what a job on a stored scan reads."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from services.db.models import Job, Scan


def scan(session: Session, scan_id: str) -> Scan | None:
    return session.get(Scan, scan_id)


def scan_job(session: Session, scan: Scan) -> Job:
    """The job that produces ``scan``."""
    return session.get(Job, scan.job_id)


def station_scans(session: Session, station: str, *, limit: int, part_id: str | None = None,
                  part_type_id: str | None = None) -> list[tuple[Scan, Job]]:
    """The station's most recent scans with their jobs, newest first, optionally only those of one part (the
    MES's identifier) or part type."""
    query = select(Scan, Job).join(Job, Scan.job_id == Job.id).where(Scan.station == station)
    if part_id is not None:
        query = query.where(Scan.part_id == part_id)
    if part_type_id is not None:
        query = query.where(Scan.part_type_id == part_type_id)
    return [(row.Scan, row.Job) for row in
            session.execute(query.order_by(Scan.created_at.desc(), Scan.id.desc()).limit(limit))]


def scan_artifacts(sessions: sessionmaker[Session], scan_id: str) -> dict[str, str]:
    """A stored scan's artifacts (name to digest), as a job on it reads them; ``LookupError`` when there is no
    such scan."""
    with sessions() as session:
        row = session.get(Scan, scan_id)
        if row is None:
            raise LookupError(f"there is no scan {scan_id!r}")
        return dict(row.artifacts)
