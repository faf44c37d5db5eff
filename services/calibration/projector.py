"""Projector calibration from structured-light captures of a board, by local homographies.

The projector is calibrated as an inverse camera: each board corner's projector pixel is
estimated from the decoded projector coordinates around the corner in the camera image
(Moreno and Taubin), then Zhang's method gives the projector intrinsics and a stereo
calibration gives the camera-to-projector pose.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
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

    Returns
    -------
    projector_points : (N, 2) array
        Projector pixel of each corner (NaN where the window had too few decoded pixels).
    found : (N,) bool array

    Notes
    -----
    Around corner c, the decoded pixels p_i -> q_i (camera to projector) are fitted by the
    homography H minimising sum ||q_i - H(p_i)||^2 (``cv2.findHomography``, least squares); the
    board is locally planar, so H is exact up to lens distortion over the window, and the
    corner's projector pixel is H(c) [1]_. Pixels are centred on c and scaled for conditioning.

    References
    ----------
    .. [1] D. Moreno, G. Taubin, "Simple, accurate, and robust projector-camera calibration",
       3DIMPVT 2012, 464-471.
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
        homography, _ = cv2.findHomography(camera, projector, 0)
        if homography is None:
            continue
        mapped = homography @ np.array([0.0, 0.0, 1.0])
        result[index] = mapped[:2] / mapped[2]
    return result, np.isfinite(result[:, 0])


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
