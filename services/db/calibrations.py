"""Calibration sets: the rows of a station's sets, and its active one (at most one per station)."""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from services.db.models import CalibrationSet


def activate_calibration(session: Session, calibration: CalibrationSet) -> None:
    """Make ``calibration`` its station's only active set (the caller commits)."""
    session.execute(update(CalibrationSet).where(CalibrationSet.station == calibration.station,
                                                 CalibrationSet.id != calibration.id).values(active=False))
    calibration.active = True


def add_calibration_set(session: Session, *, name: str, station: str, rig_sha256: str, source: str,
                        activate: bool = False) -> CalibrationSet:
    """Add a calibration set of the stored rig ``rig_sha256`` (``source``: upload or calibration), made the
    station's active one with ``activate`` (the caller commits)."""
    calibration = CalibrationSet(name=name, station=station, rig_sha256=rig_sha256, source=source)
    session.add(calibration)
    session.flush()
    if activate:
        activate_calibration(session, calibration)
    return calibration


def calibration_set(session: Session, calibration_set_id: str) -> CalibrationSet | None:
    return session.get(CalibrationSet, calibration_set_id)


def active_calibration(session: Session, station: str) -> CalibrationSet | None:
    """The set new scans of ``station`` use when they name none."""
    return session.scalar(select(CalibrationSet).where(CalibrationSet.station == station,
                                                       CalibrationSet.active.is_(True)))


def station_calibration_sets(session: Session, station: str) -> list[CalibrationSet]:
    """The station's calibration sets, newest first."""
    return list(session.scalars(select(CalibrationSet).where(CalibrationSet.station == station)
                                .order_by(CalibrationSet.created_at.desc())))
