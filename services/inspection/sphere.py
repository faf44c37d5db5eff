"""Robust least-squares sphere."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from services.inspection.robust import TUKEY_C, even_subset, form_range, parameter_std, robust_scale, tukey_weights


@dataclass(frozen=True)
class SphereFit:
    """Centre and radius; ``sphericity`` the peak-to-valley of the kept radial residuals."""

    center: np.ndarray
    radius: float
    sphericity: float
    noise: float
    radius_std: float
    count: int


def fit_sphere(points: np.ndarray) -> SphereFit:
    """Fit a sphere to points (a cap is enough) robustly.

    Parameters
    ----------
    points : (N, 3) array
        At least 4 points, mm.

    Returns
    -------
    SphereFit
        The geometric fit.

    Notes
    -----
    An algebraic fit |X|^2 = 2 c . X + (r^2 - |c|^2), linear in its unknowns, starts the geometric
    fit minimising sum rho(|X_i - c| - r) with scipy's trust-region least squares and the Cauchy
    loss at three robust sigmas [1]_, then plain least squares over the points within 4.685 robust
    sigmas; the parameter covariance is s^2 (J^T W J)^-1 with Tukey's
    weights of the final residuals.

    References
    ----------
    .. [1] C. M. Shakarji, "Least-squares fitting algorithms of the NIST algorithm testing system",
       J. Res. NIST 103(6), 1998.
    """
    points = even_subset(np.asarray(points, dtype=np.float64))
    if len(points) < 4:
        raise ValueError(f"A sphere needs at least 4 points; got {len(points)}.")
    origin = points.mean(axis=0)
    local = points - origin
    design = np.column_stack([2 * local, np.ones(len(local))])
    solution = np.linalg.lstsq(design, np.einsum("ij,ij->i", local, local), rcond=None)[0]
    centre, radius = solution[:3], np.sqrt(max(solution[3] + solution[:3] @ solution[:3], 1e-12))
    residual = np.linalg.norm(local - centre, axis=1) - radius
    scale = robust_scale(residual)

    def residuals(parameters: np.ndarray, kept: np.ndarray = local) -> np.ndarray:
        return np.linalg.norm(kept - parameters[:3], axis=1) - parameters[3]

    def jacobian(parameters: np.ndarray, kept: np.ndarray = local) -> np.ndarray:
        offset = kept - parameters[:3]
        distance = np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-12)
        return np.column_stack([-offset / distance, -np.ones(len(kept))])

    result = least_squares(residuals, np.append(centre, radius), jac=jacobian, loss="cauchy", f_scale=3 * scale)
    inliers = local[np.abs(result.fun) < TUKEY_C * robust_scale(result.fun)]
    result = least_squares(residuals, result.x, jac=jacobian, args=(inliers,))
    residual = residuals(result.x)
    scale = robust_scale(residual)
    weights = tukey_weights(residual, scale)
    std = parameter_std(jacobian(result.x), weights, scale)
    return SphereFit(center=result.x[:3] + origin, radius=float(result.x[3]),
                     sphericity=form_range(residual, weights), noise=scale, radius_std=float(std[3]),
                     count=len(points))
