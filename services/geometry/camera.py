"""OpenCV's pinhole camera model with lens distortion, for cameras and projectors alike: projection and
back-projection on arrays (the device itself is :class:`services.geometry.camera_model.CameraModel`).

A device pose (R, t) maps world to device coordinates, x_dev = R x_world + t;
lengths are in millimetres and distortion coefficients follow OpenCV's order
(k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, tau_x, tau_y]]]]).
"""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.camera_model import as_distortion, camera_center
from services.geometry.distortion import project_with_distortion, reprojection_errors

# A fixed number of iterations is cheap; the reprojection test that OpenCV's EPS criterion runs at every
# iteration costs ten times more, so it is run only on the points still off after the cheap pass.
_FAST_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 10, 0.0)
_THOROUGH_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
_UNDISTORT_TOLERANCE_PX = 1e-6


def _as_points(points: np.ndarray, dim: int, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}); got {points.shape}.")
    return points


def project_points(
    points_world: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> np.ndarray:
    """Project world points to distorted pixel coordinates.

    Parameters
    ----------
    points_world : (N, 3) array
        Points in world millimetres.
    K : (3, 3) array
        Intrinsic matrix.
    dist : (D,) array
        Distortion coefficients in OpenCV order, D in {0, 4, 5, 8, 12, 14}.
    R, t : (3, 3) and (3,) arrays
        Pose mapping world to device coordinates.

    Returns
    -------
    pixels : (N, 2) array
        Pixel coordinates (u, v), pixel centres at integers. Points behind the
        device (z <= 0) are NaN.

    Notes
    -----
    s [u, v, 1]^T = K distort(R X + t), the model of OpenCV's ``projectPoints``
    [1]_, evaluated on whole arrays (``distortion.distorted_pixels``, tested equal
    to OpenCV), about nine times faster than ``cv2.projectPoints`` on a million points.

    References
    ----------
    .. [1] OpenCV, "Camera Calibration and 3D Reconstruction", calib3d module.
    """
    points_world = _as_points(points_world, 3, "points_world")
    return project_with_distortion(points_world, K, as_distortion(dist), R, t)


def normalized_coordinates(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Undistorted normalised image coordinates (x/z, y/z) of distorted pixels.

    Parameters
    ----------
    pixels : (N, 2) array
        Distorted pixel coordinates.
    K, dist : arrays
        Intrinsic matrix and OpenCV distortion coefficients.

    Returns
    -------
    normalized : (N, 2) array
        Ideal coordinates such that ``project`` of (x, y, 1) gives ``pixels``.

    Notes
    -----
    Inverts the distortion model iteratively with OpenCV's ``undistortPoints``:
    ten iterations for every point, then up to 200 more for the points whose
    reprojection is still more than a micro-pixel off (strong distortion near
    the image corners), so the round trip is exact to a micro-pixel.
    """
    pixels = _as_points(pixels, 2, "pixels")
    K = np.asarray(K, np.float64)
    dist = as_distortion(dist)
    if pixels.shape[0] == 0:
        return np.empty((0, 2))
    if not dist.any():
        return (pixels - K[:2, 2]) / np.diag(K)[:2]
    normalized = cv2.undistortPoints(pixels.reshape(-1, 1, 2), K, dist, criteria=_FAST_UNDISTORT_CRITERIA)
    normalized = normalized.reshape(-1, 2)
    off = reprojection_errors(normalized, pixels, K, dist) > _UNDISTORT_TOLERANCE_PX
    if off.any():
        normalized[off] = cv2.undistortPoints(pixels[off].reshape(-1, 1, 2), K, dist,
                                              criteria=_THOROUGH_UNDISTORT_CRITERIA).reshape(-1, 2)
    return normalized


def pixel_rays(
    pixels: np.ndarray, K: np.ndarray, dist: np.ndarray, R: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World-space viewing rays through distorted pixels.

    Returns
    -------
    origin : (3,) array
        Device centre in world coordinates.
    directions : (N, 3) array
        Unit ray directions in world coordinates: X(s) = origin + s d.
    """
    normalized = normalized_coordinates(pixels, K, dist)
    rays_device = np.column_stack([normalized, np.ones(len(normalized))])
    directions = rays_device @ np.asarray(R, dtype=np.float64)  # R^T applied to each row
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return camera_center(R, t), directions


def pixel_grid(width: int, height: int) -> np.ndarray:
    """(height*width, 2) array of pixel centres (u, v) in row-major order."""
    v, u = np.mgrid[0:height, 0:width]
    return np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
