"""Shared pieces of the robust fits: a robust scale, Tukey weights and the parameter covariance."""

from __future__ import annotations

import numpy as np

TUKEY_C = 4.685
MIN_SCALE_MM = 1e-3
MAX_FIT_POINTS = 20000


def robust_scale(residual: np.ndarray) -> float:
    """1.4826 times the median absolute deviation, at least 1 um."""
    return max(1.4826 * float(np.median(np.abs(residual - np.median(residual)))), MIN_SCALE_MM)


def tukey_weights(residual: np.ndarray, scale: float) -> np.ndarray:
    """Tukey's biweight w = (1 - (r / c s)^2)^2 inside c s, 0 outside (c = 4.685)."""
    u = residual / (TUKEY_C * scale)
    return np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)


def even_subset(points: np.ndarray, wanted: int = MAX_FIT_POINTS) -> np.ndarray:
    """At most ``wanted`` points drawn evenly (deterministically) from the array's order."""
    if len(points) <= wanted:
        return points
    return points[np.linspace(0, len(points) - 1, wanted).astype(np.intp)]


def parameter_std(jacobian: np.ndarray, weights: np.ndarray, scale: float) -> np.ndarray:
    """Standard deviations of least-squares parameters, sqrt(diag(s^2 (J^T W J)^-1)), with ``scale`` s."""
    normal = jacobian.T @ (jacobian * weights[:, None])
    return np.sqrt(np.abs(np.diag(np.linalg.pinv(normal)))) * scale


def form_range(residual: np.ndarray, weights: np.ndarray) -> float:
    """Peak-to-valley of the residuals of the points the robust fit kept (weight > 0)."""
    kept = residual[weights > 0]
    return float(np.ptp(kept)) if len(kept) else float("nan")
