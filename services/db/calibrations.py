"""The station's active calibration set: at most one per station."""

from __future__ import annotations

from sqlalchemy import update
from sqlalchemy.orm import Session

from services.db.models import CalibrationSet


def activate_calibration(session: Session, calibration: CalibrationSet) -> None:
    """Make ``calibration`` its station's only active set (the caller commits)."""
    session.execute(update(CalibrationSet).where(CalibrationSet.station == calibration.station,
                                                 CalibrationSet.id != calibration.id).values(active=False))
    calibration.active = True
