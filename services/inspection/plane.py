"""Robust least-squares plane."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.inspection.robust import even_subset, form_range, robust_scale, tukey_weights


@dataclass(frozen=True)
class PlaneFit:
    """n . X = n . point; ``flatness`` the peak-to-valley of the kept residuals; ``noise`` the robust sigma."""

    point: np.ndarray
    normal: np.ndarray
    flatness: float
    noise: float
    point_std: float
    count: int


def fit_plane(points: np.ndarray, iterations: int = 8) -> PlaneFit:
    """Fit a plane to points robustly.

    Parameters
    ----------
    points : (N, 3) array
        At least 3 points, mm.
    iterations : int
        Reweighting rounds.

    Returns
    -------
    PlaneFit
        The plane through the weighted centroid with the weighted covariance's smallest eigenvector
        as normal.

    Notes
    -----
    Iteratively reweighted total least squares: with Tukey's biweight w_i of the residuals
    r_i = n . (X_i - c) in robust sigmas [1]_, c = sum w_i X_i / sum w_i and n the eigenvector of the
    smallest eigenvalue of sum w_i (X_i - c)(X_i - c)^T. The standard deviation of the plane's
    position along n is s / sqrt(sum w_i).

    References
    ----------
    .. [1] P. J. Huber and E. M. Ronchetti, Robust Statistics, 2nd ed., Wiley, 2009, ch. 7.
    """
    points = even_subset(np.asarray(points, dtype=np.float64))
    if len(points) < 3:
        raise ValueError(f"A plane needs at least 3 points; got {len(points)}.")
    weights = np.ones(len(points))
    scale = np.inf
    for _ in range(iterations):
        centre = (weights[:, None] * points).sum(axis=0) / weights.sum()
        offset = points - centre
        _, vectors = np.linalg.eigh((weights[:, None] * offset).T @ offset)
        normal = vectors[:, 0]
        residual = offset @ normal
        scale = robust_scale(residual)
        weights = tukey_weights(residual, scale)
        if weights.sum() < 3:
            raise ValueError("Too few points agree on a plane.")
    return PlaneFit(point=centre, normal=normal, flatness=form_range(residual, weights), noise=scale,
                    point_std=scale / np.sqrt(weights.sum()), count=len(points))
