"""The summary of a temperature field that the scan endpoint and MQTT events report."""

from __future__ import annotations

import numpy as np

PERCENTILES = (5, 25, 50, 75, 95)


def field_summary(field: dict[str, np.ndarray]) -> dict:
    """Point count, bounding box (world mm) and temperature statistics (degrees C) of a field.

    Statistics cover the points with a temperature (finite); ``temperature`` is None
    when no point has one.
    """
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    temperature = np.asarray(field["temperature"], dtype=np.float64)
    seen = temperature[np.isfinite(temperature)]
    empty = len(points) == 0
    summary = {
        "point_count": int(len(points)),
        "points_with_temperature": int(len(seen)),
        "bbox_min": [0.0, 0.0, 0.0] if empty else points.min(axis=0).round(3).tolist(),
        "bbox_max": [0.0, 0.0, 0.0] if empty else points.max(axis=0).round(3).tolist(),
        "temperature": None,
    }
    if len(seen):
        summary["temperature"] = {
            "min": round(float(seen.min()), 3),
            "max": round(float(seen.max()), 3),
            "mean": round(float(seen.mean()), 3),
            "percentiles": {f"p{p}": round(float(v), 3) for p, v in zip(PERCENTILES, np.percentile(seen, PERCENTILES))},
        }
    return summary
