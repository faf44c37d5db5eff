"""Choosing the corner refinement window from the calibration views by cross-validation."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from services.calibration.camera import DistortionModel, calibrate_camera, locate_camera
from services.calibration.corners import DEFAULT_WINDOW_FRACTION, refine_corners
from services.geometry.camera import project_points

WINDOW_FRACTIONS = (0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45)
"""Candidate half windows, as fractions of the corner spacing (the default rule is 0.25)."""
MAX_FOLDS = 5
MIN_VIEWS_TO_CHOOSE = 4  # three views leave two to calibrate each fold: too few to judge a window


@dataclass(frozen=True)
class WindowSelection:
    """The chosen refinement window and the evidence for it.

    Attributes
    ----------
    fraction : float
        The chosen half window, as a fraction of each corner's distance to its nearest neighbour.
    held_out_rms : dict of float to float
        Cross-validated reprojection RMS (px) of every candidate fraction; empty when too few views.
    image_points : list of (N_i, 2) float64 arrays
        Every view's corners refined with the chosen window.
    reason : str
        One sentence saying why this fraction.
    """

    fraction: float
    held_out_rms: dict[float, float]
    image_points: list[np.ndarray]
    reason: str


def select_corner_window(images: Sequence[np.ndarray], image_points: Sequence[np.ndarray],
                         object_points: Sequence[np.ndarray], image_size: tuple[int, int],
                         distortion: DistortionModel = "standard",
                         fractions: Sequence[float] = WINDOW_FRACTIONS) -> WindowSelection:
    """Refine every view's corners with each candidate window and keep the one that predicts held-out views best.

    Parameters
    ----------
    images : sequence of (H, W) uint8, uint16 or float32 arrays
        The board views.
    image_points : sequence of (N_i, 2) arrays
        Each view's detected corners (any refinement: they are refined again from there).
    object_points : sequence of (N_i, 3) arrays
        The corners' board coordinates, in millimetres.
    image_size : (width, height)
    distortion : {"none", "radial", "standard", "rational", "auto"}
        The lens model the calibration will use; "auto" is resolved once, on the default window's corners.
    fractions : sequence of float
        Candidate half windows as fractions of the corner spacing, each in (0, 0.5).

    Returns
    -------
    WindowSelection

    Notes
    -----
    The saddle-point refinement ``sum_i (grad I(p_i) . (p_i - q)) = 0`` [1]_ averages over its window: a
    window too small for the blur of the corner is noisy, one too large takes in the lens's curvature
    of the edges and the neighbouring squares' shading. Which size is best depends on the optics,
    the focus and the board's print, so each calibration measures it. The views are split into
    ``k = min(views, 5)`` folds; for every fold and candidate, the camera is calibrated (Zhang) from the
    other folds' views, each held-out view's pose is fitted with those intrinsics (``locate_camera``),
    and its corners' residuals are pooled into the candidate's held-out RMS [2]_. The candidate of
    lowest held-out RMS wins; with fewer than four views the default quarter is kept.

    References
    ----------
    .. [1] W. Foerstner, E. Guelch, "A fast operator for detection and precise location of distinct points,
       corners and centres of circular features", ISPRS Intercommission Workshop, Interlaken, 1987.
    .. [2] M. Stone, "Cross-validatory choice and assessment of statistical predictions", Journal of the Royal
       Statistical Society B 36(2), 111-147 (1974).
    """
    if not (len(images) == len(image_points) == len(object_points)):
        raise ValueError(f"Every view needs its image, corners and board points; got {len(images)} images, "
                         f"{len(image_points)} corner sets and {len(object_points)} board point sets.")
    if len(images) < MIN_VIEWS_TO_CHOOSE:
        refined = [refine_corners(image, points, DEFAULT_WINDOW_FRACTION) for image, points in zip(images, image_points)]
        return WindowSelection(DEFAULT_WINDOW_FRACTION, {}, refined,
                               f"{len(images)} views are too few to compare windows; the default "
                               f"{DEFAULT_WINDOW_FRACTION} of the corner spacing is kept")
    objects = [np.asarray(points, np.float64) for points in object_points]
    if distortion == "auto":
        distortion = calibrate_camera(objects, [np.asarray(p, np.float64) for p in image_points], image_size,
                                      "auto", jackknife=False).distortion_model
    candidates = {fraction: [refine_corners(image, points, fraction) for image, points in zip(images, image_points)]
                  for fraction in fractions}
    held_out = {fraction: _held_out_rms(objects, refined, image_size, distortion)
                for fraction, refined in candidates.items()}
    chosen = min(held_out, key=held_out.get)
    ranked = sorted(held_out, key=held_out.get)
    reason = (f"a half window of {chosen} of the corner spacing predicts held-out views best "
              f"({held_out[chosen]:.3f} px; next {ranked[1]}: {held_out[ranked[1]]:.3f} px)")
    return WindowSelection(chosen, held_out, candidates[chosen], reason)


def _held_out_rms(objects: list[np.ndarray], images: list[np.ndarray], image_size: tuple[int, int],
                  distortion: DistortionModel) -> float:
    """Reprojection RMS of every view's corners under intrinsics calibrated without its fold."""
    folds = min(len(objects), MAX_FOLDS)
    squared = []
    for fold in range(folds):
        held = [i for i in range(len(objects)) if i % folds == fold]
        kept = [i for i in range(len(objects)) if i % folds != fold]
        calibration = calibrate_camera([objects[i] for i in kept], [images[i] for i in kept], image_size,
                                       distortion, reject_outliers=False, jackknife=False)
        for i in held:
            R, t = locate_camera(objects[i], images[i], calibration.K, calibration.dist)
            predicted = project_points(objects[i], calibration.K, calibration.dist, R, t)
            squared.append(np.sum((predicted - images[i]) ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(squared))))
