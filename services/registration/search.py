"""Coarse global search: exhaustive MI over a grid of rotations, scales and shifts at low resolution.

A local optimiser started at the nominal alignment falls into the nearest
MI maximum; a shift of 40 px is many capture ranges at full resolution. At the
coarsest pyramid level the whole plausible range is cheap to scan: for each
(rotation, scale) the fixed image is warped once onto a moving-grid canvas
widened by the shift range, and every integer shift is then a slice of it,
scored with a hard-binned joint histogram (MI, NMI) or, for normalised
gradient fields, by correlation of structure tensors (all shifts at once).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

from services.registration.gradient_fields import gradient_epsilon, normalized_gradient_field, tensor_similarity_map
from services.registration.models import corner_error, similarity_about_centres
from services.registration.mutual_information import joint_entropies
from services.registration.objective import sample_fixed


@dataclass(frozen=True)
class Candidate:
    """One starting point for refinement: the matrix (moving to fixed pixels) and its objective value."""

    matrix: np.ndarray
    value: float


# Hand-written with numba: the inner loop over tens of thousands of shifts
# would otherwise be dominated by Python call overhead. The scan only ranks
# grid points, so it bins hard (one cell update per sample, a quarter of the
# Parzen window's cost); the refinement then uses the smooth estimator.
@numba.njit(cache=True, nogil=True)
def _scan_shifts(
    canvas: np.ndarray, moving: np.ndarray, margin: int, bins: int, log_base: float, use_nmi: bool, min_weight: float
) -> np.ndarray:
    """Objective for every integer shift (dy, dx) in [-margin, margin]^2 of bin-index images; -inf below overlap."""
    height, width = moving.shape
    values = np.full((2 * margin + 1, 2 * margin + 1), -np.inf)
    histogram = np.zeros((bins, bins))
    for dy in range(2 * margin + 1):
        for dx in range(2 * margin + 1):
            histogram[:] = 0.0
            for row in range(height):
                for column in range(width):
                    a = canvas[dy + row, dx + column]
                    if a >= 0:
                        histogram[a, moving[row, column]] += 1.0
            weight, h_fixed, h_moving, h_joint = joint_entropies(histogram)
            if weight >= min_weight and h_joint > 0.0:
                values[dy, dx] = (h_fixed + h_moving) / h_joint if use_nmi else (
                    (h_fixed + h_moving - h_joint) / np.log(log_base))
    return values


def _bin_indices(quantized: np.ndarray) -> np.ndarray:
    """Nearest bin of each quantised sample, -1 where invalid."""
    return np.where(quantized < 0.0, -1, np.rint(quantized)).astype(np.int16)


def _distinct_best(candidates: list[Candidate], count: int, width: int, height: int, spacing: float) -> list[Candidate]:
    """The ``count`` best candidates whose corner maps differ by more than ``spacing`` pixels."""
    chosen: list[Candidate] = []
    for candidate in sorted(candidates, key=lambda item: item.value, reverse=True):
        if all(corner_error(candidate.matrix, other.matrix, width, height) > spacing for other in chosen):
            chosen.append(candidate)
            if len(chosen) == count:
                break
    return chosen


_PEAKS_PER_CANVAS = 20  # best shifts kept per (rotation, scale) before choosing distinct candidates


def _best_shifts(values: np.ndarray, base: np.ndarray, margin: int) -> list[Candidate]:
    """The ``_PEAKS_PER_CANVAS`` best finite entries of one canvas's shift map as candidates, best first.

    Entry (row, column) of ``values`` is the shift d = (column - margin, row - margin) applied after ``base``.
    Keeping a few per canvas instead of every shift spares sorting and comparing tens of thousands of
    candidates of which only the few best distinct ones are kept.
    """
    candidates = []
    for index in np.argsort(values, axis=None)[::-1][:_PEAKS_PER_CANVAS]:
        row, column = np.unravel_index(index, values.shape)
        if not np.isfinite(values[row, column]):
            break
        shift = np.array([[1.0, 0.0, column - margin], [0.0, 1.0, row - margin], [0.0, 0.0, 1.0]])
        candidates.append(Candidate(base @ shift, float(values[row, column])))
    return candidates


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

    Returns
    -------
    list of Candidate
        Best first, at least 1.5 moving pixels apart at the corners.

    Notes
    -----
    The transform is H(u) = c_f + s R(theta) (u - c_m + d), with c_f and c_m
    the image centres and d the shift in moving pixels; the sampled fixed
    image for shift d is the d-offset window of the canvas warped with d = 0.
    """
    if max_shift < 0:
        raise ValueError(f"The search range must be non-negative; got max_shift={max_shift}.")
    height, width = moving.shape
    moving_centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    fixed_centre = np.array([(fixed.shape[1] - 1) / 2.0, (fixed.shape[0] - 1) / 2.0])
    margin = int(max_shift)
    canvas_to_moving = np.array([[1.0, 0.0, -margin], [0.0, 1.0, -margin], [0.0, 0.0, 1.0]])
    moving_bins = _bin_indices(moving)
    candidates = []
    for angle in angles:
        for factor in scale_factors:
            base = similarity_about_centres(moving_centre, fixed_centre, scale * factor, angle, np.zeros(2))
            canvas = sample_fixed(fixed, base @ canvas_to_moving, width + 2 * margin, height + 2 * margin)
            values = _scan_shifts(_bin_indices(canvas), moving_bins, margin, bins, log_base, metric == "nmi",
                                  min_overlap * moving.size)
            candidates += _best_shifts(values, base, margin)
    return _distinct_best(candidates, count, width, height, spacing=1.5)


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
) -> list[Candidate]:
    """Scan similarity transforms about the image centres by normalised-gradient-field similarity.

    Parameters
    ----------
    fixed, moving : 2-D float32 arrays
        Smoothed grey images at the search resolution.
    scale, angles, scale_factors, max_shift, min_overlap, count
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
    moving_x, moving_y = normalized_gradient_field(moving, gradient_epsilon(moving))
    candidates = []
    for angle in angles:
        for factor in scale_factors:
            base = similarity_about_centres(moving_centre, fixed_centre, scale * factor, angle, np.zeros(2))
            canvas = sample_fixed(fixed, base @ canvas_to_moving, width + 2 * margin, height + 2 * margin)
            values = tensor_similarity_map(*_field_canvas(canvas, fixed_epsilon), moving_x, moving_y,
                                           min_overlap * moving.size)
            candidates += _best_shifts(values, base, margin)
    return _distinct_best(candidates, count, width, height, spacing=1.5)
