"""Part types: the rows of a station's part types, and its selected one (its recipe, at most one per station)."""

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


def add_part_type(session: Session, *, name: str, station: str, material: str, part_sha256: str,
                  mesh_sha256: str, select_: bool = False) -> PartType:
    """Add a part type of the stored part file and mesh, made the station's selected one with ``select_``
    (the caller commits)."""
    part_type = PartType(name=name, station=station, material=material, part_sha256=part_sha256,
                         mesh_sha256=mesh_sha256)
    session.add(part_type)
    session.flush()
    if select_:
        select_part_type(session, part_type)
    return part_type


def part_type(session: Session, part_type_id: str) -> PartType | None:
    return session.get(PartType, part_type_id)


def station_part_types(session: Session, station: str) -> list[PartType]:
    """The station's part types, newest first."""
    return list(session.scalars(select(PartType).where(PartType.station == station)
                                .order_by(PartType.created_at.desc())))
