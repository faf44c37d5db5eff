"""Projector calibration from structured-light captures of a board, by local homographies.

The projector is calibrated as an inverse camera: each board corner's projector pixel is
estimated from the decoded projector coordinates around the corner in the camera image
(Moreno and Taubin), then Zhang's method gives the projector intrinsics and a stereo
calibration gives the camera-to-projector pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.calibration.camera import CameraCalibration, calibrate_camera
from services.calibration.stereo import StereoCalibration, calibrate_stereo

MIN_WINDOW_FILL = 0.3  # fraction of a window's pixels that must be decoded to trust its homography


@dataclass(frozen=True)
class ProjectorCalibration:
    """The result of ``calibrate_projector``: the projector as a camera, and its pose from the camera."""

    projector: CameraCalibration
    stereo: StereoCalibration


def projector_corners(
    image_points: np.ndarray,
    projector_x: np.ndarray,
    projector_y: np.ndarray,
    half_window: int,
    modulation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Projector pixels of board corners from decoded projector coordinates around them.

    Parameters
    ----------
    image_points : (N, 2) array
        Corner positions in the camera image (pixels).
    projector_x, projector_y : (H, W) arrays
        Decoded projector column and row of each camera pixel, NaN where not decoded.
    half_window : int
        The homography of each corner is fitted on the camera pixels within this many pixels
        (a square window); about half the imaged square size.
    modulation : (H, W) array, optional
        Amplitude of the decoded signal per pixel; pixels are weighted by its square (the
        inverse variance of a phase-shift coordinate), so that pixels on dark squares count
        little. Equal weights when omitted.

    Returns
    -------
    projector_points : (N, 2) array
        Projector pixel of each corner (NaN where the window had too few decoded pixels).
    found : (N,) bool array

    Notes
    -----
    Around corner c, the decoded pixels p_i -> q_i (camera to projector) are fitted by the
    homography H of the weighted direct linear transform, minimising sum w_i ||A_i h||^2 with
    A_i the two DLT rows of p_i -> q_i and ||h|| = 1 (smallest right singular vector). The
    board is locally planar, so H is exact up to lens distortion over the window, and the
    corner's projector pixel is H(c) [1]_. Camera pixels are centred on c and projector pixels
    on their weighted mean, both scaled to unit size, for conditioning [2]_.

    References
    ----------
    .. [1] D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
       3DIMPVT 2012, 464-471.
    .. [2] R. Hartley, A. Zisserman, "Multiple View Geometry in Computer Vision", 2nd ed., 2004,
       section 4.4 (normalised DLT).
    """
    image_points = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    if projector_x.shape != projector_y.shape or projector_x.ndim != 2:
        raise ValueError("projector_x and projector_y must be 2-D maps of one shape.")
    if half_window < 2:
        raise ValueError(f"half_window must be at least 2 pixels; got {half_window}.")
    height, width = projector_x.shape
    offsets = np.arange(-half_window, half_window + 1)
    result = np.full((len(image_points), 2), np.nan)
    for index, (u, v) in enumerate(image_points):
        columns = np.clip(np.round(u).astype(int) + offsets, 0, width - 1)
        rows = np.clip(np.round(v).astype(int) + offsets, 0, height - 1)
        window_x = projector_x[np.ix_(rows, columns)]
        window_y = projector_y[np.ix_(rows, columns)]
        decoded = np.isfinite(window_x) & np.isfinite(window_y)
        if decoded.sum() < max(8, MIN_WINDOW_FILL * decoded.size):
            continue
        grid_v, grid_u = np.meshgrid(rows, columns, indexing="ij")
        camera = (np.column_stack([grid_u[decoded], grid_v[decoded]]) - (u, v)) / half_window
        projector = np.column_stack([window_x[decoded], window_y[decoded]])
        weights = np.ones(len(camera)) if modulation is None else modulation[np.ix_(rows, columns)][decoded] ** 2
        result[index] = _weighted_homography_image(camera, projector, weights)
    return result, np.isfinite(result[:, 0])


def _weighted_homography_image(camera: np.ndarray, projector: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Where the weighted-DLT homography camera -> projector maps the camera origin."""
    centre = np.average(projector, axis=0, weights=weights)
    scale = np.sqrt(np.average(np.sum((projector - centre) ** 2, axis=1), weights=weights)) or 1.0
    target = (projector - centre) / scale
    x, y = camera[:, 0], camera[:, 1]
    X, Y = target[:, 0], target[:, 1]
    zeros, ones = np.zeros_like(x), np.ones_like(x)
    rows = np.concatenate([
        np.column_stack([x, y, ones, zeros, zeros, zeros, -X * x, -X * y, -X]),
        np.column_stack([zeros, zeros, zeros, x, y, ones, -Y * x, -Y * y, -Y]),
    ]) * np.sqrt(np.concatenate([weights, weights]))[:, None]
    homography = np.linalg.svd(rows, full_matrices=False)[2][-1].reshape(3, 3)
    if abs(homography[2, 2]) < 1e-12:
        return np.full(2, np.nan)
    return homography[:2, 2] / homography[2, 2] * scale + centre


def calibrate_projector(
    object_points: list[np.ndarray],
    camera_points: list[np.ndarray],
    projector_points: list[np.ndarray],
    camera_intrinsics: tuple[np.ndarray, np.ndarray],
    camera_size: tuple[int, int],
    projector_size: tuple[int, int],
    distortion: str = "radial",
) -> ProjectorCalibration:
    """Projector intrinsics and camera-to-projector pose from board corners seen by both.

    Parameters
    ----------
    object_points : list of (N_i, 3) arrays
        Board corners of each pose (board millimetres).
    camera_points, projector_points : lists of (N_i, 2) arrays
        Their camera pixels and projector pixels (from ``projector_corners``).
    camera_intrinsics : (K, dist)
        The calibrated camera.
    camera_size, projector_size : (width, height)
    distortion : str
        Projector lens model, as for ``calibrate_camera``.

    Returns
    -------
    ProjectorCalibration
        ``stereo.R, stereo.t`` map camera coordinates to projector coordinates.

    Notes
    -----
    Zhang's method on the projector points [1]_ (with its outlier-view rejection), then
    ``calibrate_stereo`` with both intrinsics fixed on the views the projector kept.

    References
    ----------
    .. [1] D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
       3DIMPVT 2012, 464-471.
    """
    projector = calibrate_camera(object_points, projector_points, projector_size, distortion)
    kept = projector.views
    stereo = calibrate_stereo([object_points[i] for i in kept], [camera_points[i] for i in kept],
                              [projector_points[i] for i in kept], camera_intrinsics,
                              (projector.K, projector.dist), camera_size)
    return ProjectorCalibration(projector=projector, stereo=stereo)
