"""Use case: the summary of a scan that the scan endpoint, MQTT events and the demo report: its temperature field
and what a hot part's glow did to it."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from services.formats.stored_scan import Exposure, FieldSummary, GlowSummary, TemperatureSummary
from services.geometry.cloud import PointCloud
from services.structured_light.glow import GlowReport

PERCENTILES = (5, 25, 50, 75, 95)


def field_summary(field: PointCloud | Mapping[str, np.ndarray]) -> FieldSummary:
    """Point count, bounding box (world mm) and temperature statistics (degrees C) of a field.

    Statistics cover the points with a temperature (finite); ``temperature`` is None
    when no point has one.
    """
    coordinates = [np.asarray(field[name]) for name in ("x", "y", "z")]
    temperature = np.asarray(field["temperature"], dtype=np.float64)
    seen = temperature[np.isfinite(temperature)]
    empty = len(coordinates[0]) == 0
    temperature = None
    if len(seen):
        temperature = TemperatureSummary(
            min=round(float(seen.min()), 3), max=round(float(seen.max()), 3), mean=round(float(seen.mean()), 3),
            percentiles={f"p{p}": round(float(v), 3) for p, v in zip(PERCENTILES, np.percentile(seen, PERCENTILES))})
    return FieldSummary(
        point_count=int(len(coordinates[0])), points_with_temperature=int(len(seen)),
        bbox_min=[0.0, 0.0, 0.0] if empty else [float(np.round(np.float64(axis.min()), 3)) for axis in coordinates],
        bbox_max=[0.0, 0.0, 0.0] if empty else [float(np.round(np.float64(axis.max()), 3)) for axis in coordinates],
        temperature=temperature)


def glow_summary(report: GlowReport | None, exposure: Exposure | Mapping[str, Any]) -> GlowSummary | None:
    """What the glow did to a scan: shares of the glowing part saturated or lost in its shot noise, the glow
    level and drift, the exposures used, and a hint when the glow cost more than 5 % of the part.

    None when the capture's sequence does not close with a black frame (no glow measurement).
    """
    if report is None:
        return None
    exposure = exposure if isinstance(exposure, Exposure) else Exposure.model_validate(dict(exposure))
    return GlowSummary.model_validate({
        **report.as_dict(), "lost_to_glow": round(report.saturated_fraction + report.lost_fraction, 5),
        "exposure_mode": exposure.mode, "exposures_us": exposure.exposures_us})
