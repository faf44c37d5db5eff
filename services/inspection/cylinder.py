"""Robust least-squares cylinder."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from services.inspection.robust import TUKEY_C, even_subset, form_range, parameter_std, robust_scale, tukey_weights


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


def axis_frame(axis: np.ndarray) -> np.ndarray:
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
    line minus r. Its Jacobian is analytic: with w the radial offset, w^ = w / |w|, s = (X - c) . d
    and n = |(alpha, beta, 1)|, dr/d(x0, y0) = -(w^_u, w^_v), dr/d(alpha, beta) = -s (w^_u, w^_v) / n
    and dr/dr0 = -1. sum rho(r_i) is minimised with scipy's trust-region least squares and the Cauchy
    loss at three robust sigmas, then plain least squares over the points within 4.685 robust sigmas
    (the Cauchy loss alone leaves a bias of a few micrometres from far outliers); the radius's
    standard deviation comes from s^2 (J^T W J)^-1 with
    Tukey's weights of the final residuals [1]_.

    References
    ----------
    .. [1] C. M. Shakarji, "Least-squares fitting algorithms of the NIST algorithm testing system",
       J. Res. NIST 103(6), 1998, sec. 3.4.
    """
    points = even_subset(np.asarray(points, dtype=np.float64))
    if len(points) < 5:
        raise ValueError(f"A cylinder needs at least 5 points; got {len(points)}.")
    frame = axis_frame(np.asarray(axis, dtype=np.float64))
    origin = np.asarray(axis_point, dtype=np.float64)
    local = (points - origin) @ frame.T

    def direction_of(parameters: np.ndarray) -> np.ndarray:
        alpha, beta = parameters[2:4]
        return np.array([alpha, beta, 1.0]) / np.sqrt(1 + alpha * alpha + beta * beta)

    def radial_parts(parameters: np.ndarray, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        direction = direction_of(parameters)
        offset = kept - np.array([parameters[0], parameters[1], 0.0])
        along = offset @ direction
        radial = offset - np.outer(along, direction)
        return radial, np.sqrt(np.einsum("ij,ij->i", radial, radial)), along

    def residuals(parameters: np.ndarray, kept: np.ndarray = local) -> np.ndarray:
        return radial_parts(parameters, kept)[1] - parameters[4]

    def jacobian(parameters: np.ndarray, kept: np.ndarray = local) -> np.ndarray:
        radial, length, along = radial_parts(parameters, kept)
        unit = radial / np.maximum(length, 1e-12)[:, None]
        tilt = along / np.sqrt(1 + parameters[2] ** 2 + parameters[3] ** 2)
        return np.column_stack([-unit[:, 0], -unit[:, 1], -tilt * unit[:, 0], -tilt * unit[:, 1],
                                -np.ones(len(kept))])

    start = np.array([0.0, 0.0, 0.0, 0.0, radius])
    start[4] += np.median(residuals(start))  # the radius the points say about the starting axis
    scale = robust_scale(residuals(start))
    result = least_squares(residuals, start, jac=jacobian, loss="cauchy", f_scale=3 * scale, x_scale="jac")
    inliers = local[np.abs(result.fun) < TUKEY_C * robust_scale(result.fun)]
    result = least_squares(residuals, result.x, jac=jacobian, x_scale="jac", args=(inliers,))
    residual = residuals(result.x)
    scale = robust_scale(residual)
    weights = tukey_weights(residual, scale)
    std = parameter_std(jacobian(result.x), weights, scale)
    direction = direction_of(result.x)
    x0, y0 = result.x[:2]
    return CylinderFit(point=origin + frame.T @ np.array([x0, y0, 0.0]), axis=frame.T @ direction,
                       radius=float(result.x[4]), cylindricity=form_range(residual, weights), noise=scale,
                       radius_std=float(std[4]), count=len(points))
