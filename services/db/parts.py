"""The station's selected part type (its recipe): at most one per station."""

from __future__ import annotations

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from services.db.models import PartType


def select_part_type(session: Session, part_type: PartType) -> None:
    """Make ``part_type`` its station's only selected one (the caller commits)."""
    session.execute(update(PartType).where(PartType.station == part_type.station,
                                           PartType.id != part_type.id).values(selected=False))
    part_type.selected = True


def selected_part_type(session: Session, station: str) -> PartType | None:
    """The part type scans of ``station`` are inspected against when they name none."""
    return session.scalar(select(PartType).where(PartType.station == station, PartType.selected.is_(True)))
