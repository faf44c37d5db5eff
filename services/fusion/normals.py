"""Surface normals of a point cloud by principal component analysis of each point's neighbours."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def estimate_normals(
    points: np.ndarray, viewpoint: np.ndarray, neighbours: int = 12, where: np.ndarray | None = None
) -> np.ndarray:
    """Unit normals of a point cloud, oriented toward a viewpoint.

    Parameters
    ----------
    points : (N, 3) array
        Points, millimetres.
    viewpoint : (3,) array
        A position that sees every point (e.g. the camera that measured the
        cloud); each normal is flipped to face it.
    neighbours : int
        Neighbourhood size, including the point itself (at least 3).
    where : (N,) bool array, optional
        Estimate only these points' normals (neighbours still come from the
        whole cloud); the others are NaN.

    Returns
    -------
    normals : (N, 3) float64 array
        Unit normals; NaN for non-finite points and those not in ``where``.

    Notes
    -----
    The normal is the eigenvector of the smallest eigenvalue of the
    neighbourhood covariance C = 1/k sum (p_i - p_mean)(p_i - p_mean)^T [1]_,
    found with scipy's cKDTree for the neighbours.

    References
    ----------
    .. [1] H. Hoppe et al., "Surface Reconstruction from Unorganized Points",
       SIGGRAPH 1992.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {points.shape}.")
    if neighbours < 3:
        raise ValueError(f"At least 3 neighbours are needed to fit a plane; got {neighbours}.")
    normals = np.full_like(points, np.nan)
    finite = np.isfinite(points).all(axis=1)
    wanted = finite if where is None else finite & np.asarray(where, dtype=bool)
    if finite.sum() < 3 or not wanted.any():
        return normals
    valid = points[finite]
    # sliding-midpoint splits build about 3x faster than median splits and query as fast here
    tree = cKDTree(valid, balanced_tree=False, compact_nodes=False)
    _, index = tree.query(points[wanted], k=min(neighbours, len(valid)), workers=-1)
    neighbourhood = valid[index] - valid[index].mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", neighbourhood, neighbourhood)
    _, vectors = np.linalg.eigh(covariance)
    estimated = vectors[:, :, 0]
    toward = np.asarray(viewpoint, dtype=np.float64) - points[wanted]
    estimated *= np.where(np.einsum("ni,ni->n", estimated, toward) < 0, -1.0, 1.0)[:, None]
    normals[wanted] = estimated
    return normals
