"""Coarse global search: exhaustive MI over a grid of rotations, scales and shifts at low resolution.

A local optimiser started at the nominal alignment falls into the nearest
MI maximum; a shift of 40 px is many capture ranges at full resolution. At the
coarsest pyramid level the whole plausible range is cheap to scan: for each
(rotation, scale) the fixed image is warped once onto a moving-grid canvas
widened by the shift range, and every integer shift is then a slice of it.
Every shift is scored at once by correlation of the normalised gradient
fields' structure tensors (a correlation by the DFT); for MI and NMI the best few
shifts of each canvas are then scored by a hard-binned joint histogram
(one ``np.bincount`` for all of them): a histogram for every shift would be
sixty times as many histogram entries.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.registration.gradient_fields import (
    FieldTemplate,
    gradient_epsilon,
    normalized_gradient_field,
    tensor_similarity_map,
)
from services.registration.models import apply_homography, image_corners, similarity_about_centres
from services.registration.objective import sample_fixed


@dataclass(frozen=True)
class Candidate:
    """One starting point for refinement: the matrix (moving to fixed pixels) and its objective value."""

    matrix: np.ndarray
    value: float


def _shift_windows(canvas: np.ndarray, shape: tuple[int, int], shifts: np.ndarray) -> np.ndarray:
    """The ``shape``-sized windows of ``canvas`` at offsets (dy, dx), stacked: (len(shifts), height, width)."""
    windows = np.lib.stride_tricks.sliding_window_view(canvas, shape)
    return windows[shifts[:, 0], shifts[:, 1]]


def _hard_binned_scores(
    canvas: np.ndarray, moving: np.ndarray, shifts: np.ndarray, bins: int, log_base: float, use_nmi: bool,
    min_weight: float,
) -> np.ndarray:
    """MI or NMI of bin-index images (-1 invalid) at each shift (dy, dx) of the canvas, one hard-binned histogram each.

    The scan only ranks grid points, so it bins hard (one cell per sample); the refinement then uses the
    smooth estimator. -inf below ``min_weight`` overlapping samples.
    """
    fixed = _shift_windows(canvas, moving.shape, shifts).reshape(len(shifts), -1).astype(np.int32)
    cells = fixed * bins + moving.ravel() + (np.arange(len(shifts), dtype=np.int32) * bins * bins)[:, None]
    cells = cells[(fixed >= 0) & (moving.ravel() >= 0)]
    joint = np.bincount(cells, minlength=len(shifts) * bins * bins).reshape(len(shifts), bins, bins)
    total = joint.sum(axis=(1, 2)).astype(np.float64)
    p = joint / np.maximum(total, 1.0)[:, None, None]

    def entropy(probabilities: np.ndarray, axes: tuple[int, ...]) -> np.ndarray:
        return -np.sum(probabilities * np.log(np.where(probabilities > 0.0, probabilities, 1.0)), axis=axes)

    h_fixed, h_moving, h_joint = entropy(p.sum(axis=2), (1,)), entropy(p.sum(axis=1), (1,)), entropy(p, (1, 2))
    positive = h_joint > 0.0
    safe_joint = np.where(positive, h_joint, 1.0)
    values = (h_fixed + h_moving) / safe_joint if use_nmi else (h_fixed + h_moving - h_joint) / np.log(log_base)
    return np.where((total >= min_weight) & positive, values, -np.inf)


def _bin_indices(quantized: np.ndarray) -> np.ndarray:
    """Nearest bin of each quantised sample, -1 where invalid."""
    return np.where(quantized < 0.0, -1, np.rint(quantized)).astype(np.int16)


_Shift = tuple[float, np.ndarray, int, int]  # a canvas's shift: its value, the canvas's matrix and the shift (dx, dy)


def _distinct_best(shifts: list[_Shift], count: int, width: int, height: int, spacing: float) -> list[Candidate]:
    """The ``count`` best shifts whose corner maps differ by more than ``spacing`` pixels, as candidates.

    The matrix of a shift and the images of its corners are computed only for the shifts examined, best
    first (the distance is :func:`services.registration.models.corner_error`'s, term for term).
    """
    corners = image_corners(width, height)
    chosen: list[tuple[Candidate, np.ndarray]] = []
    for value, base, dx, dy in sorted(shifts, key=lambda item: item[0], reverse=True):
        matrix = base @ np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
        mapped = apply_homography(matrix, corners)
        if all(float(np.linalg.norm(mapped - other, axis=1).mean()) > spacing for _, other in chosen):
            chosen.append((Candidate(matrix, value), mapped))
            if len(chosen) == count:
                break
    return [candidate for candidate, _ in chosen]


_PEAKS_PER_CANVAS = 20  # best shifts kept per (rotation, scale) before choosing distinct candidates
_PROPOSALS_PER_CANVAS = 6  # best shifts by gradient fields per (rotation, scale) that MI and NMI then score


def _best_shifts(values: np.ndarray, count: int = _PEAKS_PER_CANVAS) -> np.ndarray:
    """The (row, column) indices of the ``count`` best finite entries of a shift map, best first.

    Keeping a few per canvas instead of every shift spares sorting and comparing tens of thousands of
    candidates of which only the few best distinct ones are kept.
    """
    best = np.argsort(values, axis=None)[::-1][:count]
    best = best[np.isfinite(values.ravel()[best])]
    return np.stack(np.unravel_index(best, values.shape), axis=1)


def _shift_candidates(base: np.ndarray, shifts: np.ndarray, values: np.ndarray, margin: int) -> list[_Shift]:
    """``base`` followed by the shift d = (column - margin, row - margin) of each (row, column) of finite value,
    for :func:`_distinct_best`, which makes candidates of the few it keeps."""
    return [(float(value), base, int(column) - margin, int(row) - margin)
            for (row, column), value in zip(shifts, values) if np.isfinite(value)]


def coarse_search(
    fixed: np.ndarray,
    moving: np.ndarray,
    scale: float,
    angles: np.ndarray,
    scale_factors: np.ndarray,
    max_shift: int,
    bins: int,
    log_base: float,
    metric: str = "nmi",
    min_overlap: float = 0.3,
    count: int = 6,
    moving_valid: np.ndarray | None = None,
) -> list[Candidate]:
    """Scan similarity transforms about the image centres and return the best distinct ones.

    Parameters
    ----------
    fixed, moving : 2-D float32 arrays
        Images quantised to [0, bins - 1] (invalid pixels negative), at the
        search resolution.
    scale : float
        Nominal fixed pixels per moving pixel.
    angles : 1-D array
        Rotations to try, radians.
    scale_factors : 1-D array
        Multipliers of ``scale`` to try.
    max_shift : int
        Shifts from -max_shift to max_shift moving pixels in x and y, step 1.
    bins, log_base : int, float
        Histogram bins and logarithm base of the objective.
    metric : {"mi", "nmi"}
        Objective to maximise.
    min_overlap : float
        Least fraction of moving pixels that must land on the fixed image.
    count : int
        Number of candidates returned.
    moving_valid : 2-D bool array, optional
        The moving pixels that have data (all by default); the others are
        left out of every score, and ``min_overlap`` is a fraction of these.

    Returns
    -------
    list of Candidate
        Best first, at least 1.5 moving pixels apart at the corners.

    Notes
    -----
    The transform is H(u) = c_f + s R(theta) (u - c_m + d), with c_f and c_m
    the image centres and d the shift in moving pixels; the sampled fixed
    image for shift d is the d-offset window of the canvas warped with d = 0.
    The shifts scored by MI or NMI are the ``_PROPOSALS_PER_CANVAS`` best of
    each canvas by the structure-tensor similarity of the two images'
    normalised gradient fields (:func:`gradient_field_search`'s score), which
    is blind to contrast, like MI.
    """
    if max_shift < 0:
        raise ValueError(f"The search range must be non-negative; got max_shift={max_shift}.")
    height, width = moving.shape
    moving_centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    fixed_centre = np.array([(fixed.shape[1] - 1) / 2.0, (fixed.shape[0] - 1) / 2.0])
    margin = int(max_shift)
    canvas_to_moving = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])
    moving_bins = _bin_indices(moving if moving_valid is None else np.where(moving_valid, moving, -1.0))
    fixed_epsilon = gradient_epsilon(fixed)
    template = _moving_template(moving, moving_valid, (height + 2 * margin, width + 2 * margin))
    min_weight = min_overlap * _moving_count(moving, moving_valid)
    candidates: list[_Shift] = []
    for angle in angles:
        for factor in scale_factors:
            base = similarity_about_centres(moving_centre, fixed_centre, scale * factor, angle, np.zeros(2))
            canvas = sample_fixed(fixed, base @ canvas_to_moving, width + 2 * margin, height + 2 * margin)
            proposals = _best_shifts(tensor_similarity_map(*_field_canvas(canvas, fixed_epsilon), template,
                                                           min_weight), _PROPOSALS_PER_CANVAS)
            values = _hard_binned_scores(_bin_indices(canvas), moving_bins, proposals, bins, log_base,
                                         metric == "nmi", min_weight)
            candidates += _shift_candidates(base, proposals, values, margin)
    return _distinct_best(candidates, count, width, height, spacing=1.5)


def _moving_template(
    moving: np.ndarray, moving_valid: np.ndarray | None, canvas_shape: tuple[int, int]
) -> FieldTemplate:
    """The moving image's gradient field prepared for the canvases, only where it has data."""
    return FieldTemplate(*normalized_gradient_field(moving, gradient_epsilon(moving, moving_valid)), canvas_shape,
                         moving_valid)


def _moving_count(moving: np.ndarray, moving_valid: np.ndarray | None) -> int:
    """The number of moving pixels that have data."""
    return moving.size if moving_valid is None else int(np.count_nonzero(moving_valid))


def _field_canvas(canvas: np.ndarray, epsilon: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gradient field of a sampled canvas, zero where a central difference would touch the outside."""
    valid = cv2.erode((canvas >= 0.0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    field_x, field_y = normalized_gradient_field(np.where(canvas >= 0.0, canvas, 0.0), epsilon)
    return field_x * valid, field_y * valid, valid


def gradient_field_search(
    fixed: np.ndarray,
    moving: np.ndarray,
    scale: float,
    angles: np.ndarray,
    scale_factors: np.ndarray,
    max_shift: int,
    min_overlap: float = 0.3,
    count: int = 6,
    moving_valid: np.ndarray | None = None,
) -> list[Candidate]:
    """Scan similarity transforms about the image centres by normalised-gradient-field similarity.

    Parameters
    ----------
    fixed, moving : 2-D float32 arrays
        Smoothed grey images at the search resolution.
    scale, angles, scale_factors, max_shift, min_overlap, count, moving_valid
        As :func:`coarse_search`.

    Returns
    -------
    list of Candidate
        Best first, at least 1.5 moving pixels apart at the corners.

    Notes
    -----
    Same transforms H(u) = c_f + s R(theta) (u - c_m + d) as
    :func:`coarse_search`; for each (theta, s) the field of the warped canvas
    is compared with the moving field at every shift d by
    :func:`services.registration.gradient_fields.tensor_similarity_map`.
    """
    if max_shift < 0:
        raise ValueError(f"The search range must be non-negative; got max_shift={max_shift}.")
    height, width = moving.shape
    moving_centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    fixed_centre = np.array([(fixed.shape[1] - 1) / 2.0, (fixed.shape[0] - 1) / 2.0])
    margin = int(max_shift)
    canvas_to_moving = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])
    fixed_epsilon = gradient_epsilon(fixed)
    template = _moving_template(moving, moving_valid, (height + 2 * margin, width + 2 * margin))
    min_weight = min_overlap * _moving_count(moving, moving_valid)
    candidates: list[_Shift] = []
    for angle in angles:
        for factor in scale_factors:
            base = similarity_about_centres(moving_centre, fixed_centre, scale * factor, angle, np.zeros(2))
            canvas = sample_fixed(fixed, base @ canvas_to_moving, width + 2 * margin, height + 2 * margin)
            values = tensor_similarity_map(*_field_canvas(canvas, fixed_epsilon), template, min_weight)
            shifts = _best_shifts(values)
            candidates += _shift_candidates(base, shifts, values[shifts[:, 0], shifts[:, 1]], margin)
    return _distinct_best(candidates, count, width, height, spacing=1.5)
