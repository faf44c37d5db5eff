"""Robust least-squares cylinder."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from services.inspection.robust import (even_subset, form_range, numeric_jacobian, parameter_std, robust_scale,
                                       tukey_weights)


@dataclass(frozen=True)
class CylinderFit:
    """Axis (a point on it and a unit direction) and radius; ``cylindricity`` the kept residuals' range."""

    point: np.ndarray
    axis: np.ndarray
    radius: float
    cylindricity: float
    noise: float
    radius_std: float
    count: int


def _frame(axis: np.ndarray) -> np.ndarray:
    """Rows u, v, axis: an orthonormal frame whose third row is the axis."""
    axis = axis / np.linalg.norm(axis)
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(axis, u), axis])


def fit_cylinder(points: np.ndarray, axis_point: np.ndarray, axis: np.ndarray, radius: float) -> CylinderFit:
    """Fit a cylinder to points (a one-sided view is enough) robustly, from a starting axis and radius.

    Parameters
    ----------
    points : (N, 3) array
        At least 5 points, mm.
    axis_point, axis : (3,) arrays
        A starting point on the axis and its direction (e.g. the nominal's, aligned).
    radius : float
        Starting radius, mm.

    Returns
    -------
    CylinderFit
        The geometric fit.

    Notes
    -----
    In a frame (u, v, a) with a the starting axis, the axis is the line through (x0, y0, 0) with
    direction (alpha, beta, 1) / |(alpha, beta, 1)| and the residual of X is its distance from that
    line minus r. sum rho(r_i) is minimised with scipy's trust-region least squares and the Cauchy
    loss at three robust sigmas; the radius's standard deviation comes from s^2 (J^T W J)^-1 with
    Tukey's weights of the final residuals [1]_.

    References
    ----------
    .. [1] C. M. Shakarji, "Least-squares fitting algorithms of the NIST algorithm testing system",
       J. Res. NIST 103(6), 1998, sec. 3.4.
    """
    points = even_subset(np.asarray(points, dtype=np.float64))
    if len(points) < 5:
        raise ValueError(f"A cylinder needs at least 5 points; got {len(points)}.")
    frame = _frame(np.asarray(axis, dtype=np.float64))
    origin = np.asarray(axis_point, dtype=np.float64)
    local = (points - origin) @ frame.T

    def geometry(parameters: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x0, y0, alpha, beta, _ = parameters
        direction = np.array([alpha, beta, 1.0]) / np.sqrt(1 + alpha * alpha + beta * beta)
        offset = local - np.array([x0, y0, 0.0])
        radial = offset - np.outer(offset @ direction, direction)
        return direction, radial, np.linalg.norm(radial, axis=1)

    def residuals(parameters: np.ndarray) -> np.ndarray:
        return geometry(parameters)[2] - parameters[4]

    start = np.array([0.0, 0.0, 0.0, 0.0, radius])
    scale = robust_scale(residuals(start))
    result = least_squares(residuals, start, loss="cauchy", f_scale=3 * scale, x_scale="jac")
    residual = result.fun
    scale = robust_scale(residual)
    weights = tukey_weights(residual, scale)
    std = parameter_std(numeric_jacobian(residuals, result.x), weights, scale)
    direction, _, _ = geometry(result.x)
    x0, y0 = result.x[:2]
    return CylinderFit(point=origin + frame.T @ np.array([x0, y0, 0.0]), axis=frame.T @ direction,
                       radius=float(result.x[4]), cylindricity=form_range(residual, weights), noise=scale,
                       radius_std=float(std[4]), count=len(points))
