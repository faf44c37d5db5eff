"""OpenCV's lens distortion model on whole arrays, for code that projects millions of points
(``cv2.projectPoints`` costs about 0.5 s per million points, several times these array expressions)."""

from __future__ import annotations

import numpy as np

from services.geometry.rigid import rigid_transform


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


def distorted_pixels(x: np.ndarray, y: np.ndarray, K: np.ndarray, terms: np.ndarray,
                     tilt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (u, v) of ideal normalised points (x, y) under OpenCV's distortion model.

    Parameters
    ----------
    x, y : arrays of one shape
        Undistorted normalised coordinates (X/Z, Y/Z).
    K : (3, 3) array
        Intrinsic matrix.
    terms, tilt : arrays
        From :func:`opencv_distortion_terms`.

    Returns
    -------
    u, v : arrays of the shape of ``x``
        Distorted pixel coordinates, in the dtype of ``x`` and ``y``.

    Notes
    -----
    With r^2 = x^2 + y^2, OpenCV's model [1]_ is
    x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    + s1 r^2 + s2 r^4 (and y' alike), then the sensor tilt [x'', y'', w] = T [x', y', 1] and
    u = f_x x'' / w + c_x. Terms whose coefficients are all zero are skipped.

    References
    ----------
    .. [1] OpenCV, "Camera Calibration and 3D Reconstruction", calib3d module.
    """
    k = terms
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[4]))
    if k[5] or k[6] or k[7]:
        radial /= 1.0 + r2 * (k[5] + r2 * (k[6] + r2 * k[7]))
    xy2 = 2.0 * x * y
    xd = x * radial + k[2] * xy2 + k[3] * (r2 + 2.0 * x * x)
    yd = y * radial + k[2] * (r2 + 2.0 * y * y) + k[3] * xy2
    if k[8] or k[9] or k[10] or k[11]:
        r4 = r2 * r2
        xd += k[8] * r2 + k[9] * r4
        yd += k[10] * r2 + k[11] * r4
    if not np.array_equal(tilt, np.eye(3)):
        w = tilt[2, 0] * xd + tilt[2, 1] * yd + tilt[2, 2]
        xd, yd = ((tilt[0, 0] * xd + tilt[0, 1] * yd + tilt[0, 2]) / w,
                  (tilt[1, 0] * xd + tilt[1, 1] * yd + tilt[1, 2]) / w)
    return K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]


def project_with_distortion(points: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray,
                            t: np.ndarray) -> np.ndarray:
    """Pixels of world points (NaN behind the device) by :func:`distorted_pixels`; see ``camera.project_points``."""
    terms, tilt = opencv_distortion_terms(dist)
    device = rigid_transform(points, R, np.asarray(t, dtype=np.float64).ravel())
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(device[:, 2] > 0.0, device[:, 2], np.nan)
        u, v = distorted_pixels(device[:, 0] / z, device[:, 1] / z, np.asarray(K, dtype=np.float64), terms, tilt)
    return np.column_stack([u, v])


def reprojection_errors(normalized: np.ndarray, pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Largest of |du|, |dv| between the projection of normalised points and the given pixels."""
    terms, tilt = opencv_distortion_terms(dist)
    normalized = np.asarray(normalized, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    u, v = distorted_pixels(normalized[:, 0], normalized[:, 1], np.asarray(K, dtype=np.float64), terms, tilt)
    return np.maximum(np.abs(u - pixels[:, 0]), np.abs(v - pixels[:, 1]))
