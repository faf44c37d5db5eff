"""OpenCV's lens distortion model as a compiled per-point function, for kernels that project millions of
points (``cv2.projectPoints`` costs about 0.5 s per million points, ten times this)."""

from __future__ import annotations

import numba
import numpy as np


def opencv_distortion_terms(dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split OpenCV distortion coefficients into the 12 polynomial terms and the 3x3 sensor-tilt matrix.

    Parameters
    ----------
    dist : (D,) array
        k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]], D in {0, 4, 5, 8, 12, 14}.

    Returns
    -------
    terms : (12,) float64 array
        k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4, zero-padded.
    tilt : (3, 3) float64 array
        OpenCV's ``computeTiltProjectionMatrix(tau_x, tau_y)`` (the identity without tilt).
    """
    coefficients = np.zeros(14)
    dist = np.asarray(dist, dtype=np.float64).ravel()
    coefficients[: dist.size] = dist
    cx, sx = np.cos(coefficients[12]), np.sin(coefficients[12])
    cy, sy = np.cos(coefficients[13]), np.sin(coefficients[13])
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array([[rot_xy[2, 2], 0, -rot_xy[0, 2]], [0, rot_xy[2, 2], -rot_xy[1, 2]], [0, 0, 1]])
    return coefficients[:12].copy(), proj_z @ rot_xy


@numba.njit(cache=True, inline="always")
def distorted_pixel(x, y, fx, fy, cx, cy, k, tilt):
    """Pixel (u, v) of the ideal normalised point (x, y) under OpenCV's model (``k``, ``tilt`` from
    :func:`opencv_distortion_terms`)."""
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k[0] * r2 + k[1] * r4 + k[4] * r6) / (1.0 + k[5] * r2 + k[6] * r4 + k[7] * r6)
    xd = x * radial + 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x) + k[8] * r2 + k[9] * r4
    yd = y * radial + k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y + k[10] * r2 + k[11] * r4
    w = tilt[2, 0] * xd + tilt[2, 1] * yd + tilt[2, 2]
    u = fx * (tilt[0, 0] * xd + tilt[0, 1] * yd + tilt[0, 2]) / w + cx
    v = fy * (tilt[1, 0] * xd + tilt[1, 1] * yd + tilt[1, 2]) / w + cy
    return u, v


@numba.njit(parallel=True, cache=True)
def _reprojection_errors(normalized, pixels, fx, fy, cx, cy, k, tilt, out):
    for i in numba.prange(normalized.shape[0]):
        u, v = distorted_pixel(normalized[i, 0], normalized[i, 1], fx, fy, cx, cy, k, tilt)
        out[i] = max(abs(u - pixels[i, 0]), abs(v - pixels[i, 1]))


@numba.njit(parallel=True, cache=True)
def _project_kernel(points, R, t, fx, fy, cx, cy, k, tilt, out):
    for i in numba.prange(points.shape[0]):
        X = R[0, 0] * points[i, 0] + R[0, 1] * points[i, 1] + R[0, 2] * points[i, 2] + t[0]
        Y = R[1, 0] * points[i, 0] + R[1, 1] * points[i, 1] + R[1, 2] * points[i, 2] + t[1]
        Z = R[2, 0] * points[i, 0] + R[2, 1] * points[i, 1] + R[2, 2] * points[i, 2] + t[2]
        if Z <= 0.0:
            out[i, 0] = out[i, 1] = np.nan
        else:
            out[i, 0], out[i, 1] = distorted_pixel(X / Z, Y / Z, fx, fy, cx, cy, k, tilt)


def project_with_distortion(points: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                            t: np.ndarray) -> np.ndarray:
    """Pixels of world points (NaN behind the device) by the compiled model; see ``camera.project_points``."""
    k, tilt = opencv_distortion_terms(dist)
    K = np.asarray(K, dtype=np.float64)
    out = np.empty((len(points), 2))
    _project_kernel(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(R, dtype=np.float64),
                    np.asarray(t, dtype=np.float64).ravel(), K[0, 0], K[1, 1], K[0, 2], K[1, 2], k, tilt, out)
    return out


def reprojection_errors(normalized: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Largest of |du|, |dv| between the projection of normalised points and the given pixels."""
    k, tilt = opencv_distortion_terms(dist)
    out = np.empty(len(normalized))
    K = np.asarray(K, dtype=np.float64)
    _reprojection_errors(np.ascontiguousarray(normalized, dtype=np.float64),
                         np.ascontiguousarray(pixels, dtype=np.float64), K[0, 0], K[1, 1], K[0, 2], K[1, 2], k, tilt,
                         out)
    return out
