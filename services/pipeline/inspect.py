"""Use case: a temperature field and a part (type) to the inspection report, the deviation clouds and the verdict.

Called by ``thermofield inspect`` and by the scan use case (:func:`services.pipeline.scan.process_scan`) when a
scan has a part type; the science is :func:`services.inspection.inspect.inspect_field`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.errors import InputError
from services.formats.part import Part
from services.formats.ply import cloud_to_ply
from services.formats.stored_scan import DEVIATION, REPORT
from services.inspection.inspect import (Inspection, PreparedPart, cold_cloud, deviation_cloud, inspect_field,
                                         prepare_part, report_json)


@dataclass(frozen=True)
class InspectionOutcome:
    """An inspection and the clouds made from it.

    ``cold``: the part's points at their cold-equivalent positions with ``deviation`` (mm) and deviation
    colours (``deviation.ply`` of a scan, ``--cold-cloud`` of the command); ``deviation``: the field as
    measured with ``deviation`` and deviation colours (``--deviation``).
    """

    inspection: Inspection
    cold: dict[str, np.ndarray]
    deviation: dict[str, np.ndarray]

    @property
    def report(self) -> dict[str, Any]:
        return self.inspection.report

    @property
    def verdict(self) -> str:
        return self.inspection.report["verdict"]


def prepare_part_type(part: Part) -> PreparedPart:
    """A part's nominal surface and feature fits, once per part type; an ``InputError`` names the part file."""
    try:
        return prepare_part(part)
    except ValueError as error:
        raise InputError(f"{part.source}: {error}") from None


def inspect_part(*, field: Mapping[str, np.ndarray], part: Part | PreparedPart,
                 source: str = "the field") -> InspectionOutcome:
    """Inspect a temperature field against a part: cold-equivalent geometry, alignment, features, surface
    deviation and verdicts (see :func:`services.inspection.inspect.inspect_field`).

    Raises
    ------
    InputError
        Naming the part file when its features miss the nominal, or ``source`` when the field lacks a
        temperature or shows no part hot enough.
    """
    prepared = part if isinstance(part, PreparedPart) else prepare_part_type(part)
    properties = dict(field.items())
    try:
        inspection = inspect_field(field=properties, part=prepared)
    except ValueError as error:
        raise InputError(f"{source}: {error}") from None
    return InspectionOutcome(inspection, cold_cloud(properties, inspection, prepared.part),
                             deviation_cloud(properties, inspection, prepared.part))


def inspection_artifacts(outcome: InspectionOutcome) -> dict[str, bytes]:
    """The files an inspected scan keeps: ``report.json`` and ``deviation.ply`` (the cold-equivalent cloud)."""
    return {REPORT.name: report_json(outcome.report).encode(), DEVIATION.name: cloud_to_ply(outcome.cold)}


def report_digest(report: Mapping[str, Any]) -> dict[str, Any]:
    """What the scan's record, its job result, MQTT and OPC UA carry of a report: the verdict, the part and
    the features (JSON-safe)."""
    safe = json.loads(report_json(report))  # non-finite numbers as null
    return {"verdict": safe["verdict"], "part": safe["part"], "features": safe["features"]}
