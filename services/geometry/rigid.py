"""Rigid motion of point arrays, y = R x + t, by OpenCV."""

from __future__ import annotations

import cv2
import numpy as np


def rigid_transform(points: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Apply a rigid (or any affine) map to points.

    Parameters
    ----------
    points : (N, 3) array
        Points, mm.
    rotation : (3, 3) array
        R.
    translation : (3,) array
        t, mm.

    Returns
    -------
    (N, 3) float64 array
        y_i = R x_i + t.

    Notes
    -----
    ``cv2.transform`` runs one pass over the points on one thread. numpy's ``points @ R.T`` hands the
    (N, 3) x (3, 3) product to the multithreaded BLAS, which on a busy 2-core machine spins its
    threads for ten times the work.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {points.shape}.")
    matrix = np.hstack([np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64)[:, None]])
    if len(points) == 0:
        return np.zeros((0, 3))
    return cv2.transform(points[:, None, :], matrix)[:, 0, :]
