"""Mutual information and normalised mutual information from a Parzen-windowed joint histogram.

Estimator: a joint histogram of ``bins`` x ``bins`` cells in which every sample
is spread over the four nearest cells with bilinear weights (a first-order
B-spline Parzen window, as in partial-volume interpolation). Compared with a
hard-binned histogram this makes MI a continuous, piecewise-smooth function of
the intensities, hence of the transform parameters, which a derivative-free
optimiser needs to reach sub-pixel accuracy; compared with Mattes' cubic
B-spline window it costs four cell updates per sample instead of sixteen.
The histogram is four weighted ``np.bincount`` calls, one per neighbouring cell.
"""

from __future__ import annotations

import numpy as np

DEFAULT_BINS = 32
DEFAULT_LOG_BASE = 2.0


class MovingWindow:
    """The moving image's half of the bilinear Parzen window, computed once per image (see :func:`moving_window`).

    ``column`` is each sample's lower bin, ``down`` and ``up`` the weights of that bin and the one above,
    both zero where the sample is invalid. The window also keeps the per-sample work arrays of the fixed
    side, reused by every histogram against it: allocating a dozen arrays of a full image for each of the
    optimiser's evaluations cost more (page faults) than the arithmetic. So one window serves one thread.
    """

    def __init__(self, column: np.ndarray, down: np.ndarray, up: np.ndarray) -> None:
        self.column, self.down, self.up = column, down, up
        size = column.size
        self._floor = np.empty(size, np.float32)
        self._fixed_up = np.empty(size, np.float32)
        self._fixed_down = np.empty(size, np.float32)
        self._valid = np.empty(size, bool)
        self._cell = np.empty(size, np.intp)
        self._weights = np.empty(size, np.float64)  # np.bincount converts other weights to float64
        self._slope = np.empty(size, np.float64)


def moving_window(moving: np.ndarray, bins: int) -> MovingWindow:
    """The Parzen-window terms of an image scaled to [0, bins - 1] (negatives invalid), flattened."""
    moving = np.ravel(moving).astype(np.float32)
    valid = (moving >= 0.0).astype(np.float32)
    column = np.clip(moving.astype(np.intp), 0, bins - 2)
    up = np.minimum(moving - column, 1.0).astype(np.float64) * valid
    return MovingWindow(column, valid - up, up)


def _fixed_window(fixed: np.ndarray, window: MovingWindow, bins: int) -> None:
    """The fixed samples' lower bins (as joint cells with the moving column) and weights, in the window's arrays."""
    fixed = np.ravel(fixed)
    if fixed.size != window.column.size:
        raise ValueError(f"The fixed samples ({fixed.size}) must match the moving window's pixels "
                         f"({window.column.size}).")
    row = np.floor(fixed, out=window._floor)
    np.clip(row, 0.0, bins - 2.0, out=row)
    up = np.subtract(fixed, row, out=window._fixed_up)
    np.minimum(up, 1.0, out=up)
    valid = np.greater_equal(fixed, 0.0, out=window._valid)  # invalid samples weigh nothing
    np.multiply(up, valid, out=up)
    np.subtract(valid, up, out=window._fixed_down)
    np.multiply(row, bins, out=window._cell, casting="unsafe")
    np.add(window._cell, window.column, out=window._cell)


def _window_histogram(window: MovingWindow, bins: int) -> np.ndarray:
    """The joint histogram of the fixed samples last put in the window by :func:`_fixed_window`."""
    def counts(fixed_weight: np.ndarray, moving_weight: np.ndarray) -> np.ndarray:
        np.multiply(fixed_weight, moving_weight, out=window._weights)
        return np.bincount(window._cell, window._weights, bins * bins).reshape(bins, bins)

    histogram = counts(window._fixed_down, window.down)
    histogram[1:, :] += counts(window._fixed_up, window.down)[:-1, :]  # the row above each sample's lower bin
    histogram[:, 1:] += counts(window._fixed_down, window.up)[:, :-1]  # the column above
    histogram[1:, 1:] += counts(window._fixed_up, window.up)[:-1, :-1]
    return histogram


def windowed_joint_histogram(fixed: np.ndarray, window: MovingWindow, bins: int) -> np.ndarray:
    """Bilinear-Parzen joint histogram of a fixed image scaled to [0, bins - 1] (negatives skipped) and a window."""
    _fixed_window(np.asarray(fixed, dtype=np.float32), window, bins)
    return _window_histogram(window, bins)


def quantized_joint_histogram(fixed: np.ndarray, moving: np.ndarray, bins: int) -> np.ndarray:
    """Bilinear-Parzen joint histogram of images already scaled to [0, bins - 1]; negatives are skipped."""
    return windowed_joint_histogram(fixed, moving_window(moving, bins), bins)


def _entropy(probabilities: np.ndarray) -> float:
    """-sum p log p over the non-zero entries (natural logarithm)."""
    p = probabilities[probabilities > 0.0]
    return float(-(p * np.log(p)).sum())


def joint_entropies(joint: np.ndarray) -> tuple[float, float, float, float]:
    """Total weight and natural-log entropies H(A), H(B), H(A, B) of a joint histogram."""
    total = float(joint.sum())
    if total <= 0.0:
        return total, 0.0, 0.0, 0.0
    p = joint / total
    return total, _entropy(p.sum(axis=1)), _entropy(p.sum(axis=0)), _entropy(p)


def quantized_information(
    fixed: np.ndarray, moving: np.ndarray | MovingWindow, bins: int, log_base: float
) -> tuple[float, float, float]:
    """MI, NMI and overlap weight of quantised images (see :func:`information_from_histogram`).

    ``moving`` may be given as its :func:`moving_window`, which spares recomputing it for every fixed image.
    """
    window = moving if isinstance(moving, MovingWindow) else moving_window(moving, bins)
    total, h_fixed, h_moving, h_joint = joint_entropies(windowed_joint_histogram(fixed, window, bins))
    if h_joint <= 0.0:
        return 0.0, 1.0, total
    return (h_fixed + h_moving - h_joint) / np.log(log_base), (h_fixed + h_moving) / h_joint, total


def information_slope(
    fixed: np.ndarray, window: MovingWindow, bins: int, log_base: float, metric: str
) -> tuple[float, float, np.ndarray]:
    """MI or NMI of fixed samples against a moving window, the overlap weight, and the value's slope per sample.

    Parameters
    ----------
    fixed : array
        Fixed samples scaled to [0, bins - 1], negatives invalid, as many as the window's pixels.
    window : MovingWindow
        The moving image's :func:`moving_window`.
    bins : int
        Bins per image.
    log_base : float
        Logarithm base of MI.
    metric : {"mi", "nmi"}
        The value differentiated.

    Returns
    -------
    value : float
        MI (in units of ``log_base``) or NMI.
    weight : float
        Summed weight of the overlapping samples.
    slope : (N,) float64 array
        d value / d f_s for each fixed sample f_s; 0 where invalid. It is the window's work array,
        overwritten by the next call.

    Notes
    -----
    With p = h / W the normalised joint histogram (W, the overlap weight, does not change under a small
    move) and the bilinear window, a sample f with lower bin r and moving weights w_m(c) moves weight from
    cell (r, c) to (r + 1, c) as f grows, so

        d value / d f = (1 / W) sum_c w_m(c) (D[r + 1, c] - D[r, c]),   D = d value / d p,

    where, up to terms that depend on the column c only and cancel in the difference,
    D_ij = (log p_ij - log p_i) / log(base) for MI = H(A) + H(B) - H(A, B) (p_i the fixed marginal; the
    moving marginal does not change), and D_ij = (NMI log p_ij - log p_i) / H(A, B) for
    NMI = (H(A) + H(B)) / H(A, B). Chained with the image gradient and the transform's Jacobian this is
    the analytic gradient of Mattes et al. [1]_ and Thevenaz and Unser [2]_ for a first-order B-spline window.
    Empty cells contribute nothing (as in ITK's Mattes metric): a sample exactly on a bin edge would
    otherwise have an infinite slope towards the empty neighbour.

    References
    ----------
    .. [1] D. Mattes et al., "PET-CT image registration in the chest using free-form deformations",
       IEEE TMI 22(1), 2003.
    .. [2] P. Thevenaz, M. Unser, "Optimization of mutual information for multiresolution image
       registration", IEEE TIP 9(12), 2000.
    """
    if metric not in ("mi", "nmi"):
        raise ValueError(f"The slope is defined for MI and NMI; got the metric {metric!r}.")
    _fixed_window(np.asarray(fixed, dtype=np.float32), window, bins)
    histogram = _window_histogram(window, bins)
    total, h_fixed, h_moving, h_joint = joint_entropies(histogram)
    slope = window._slope
    if h_joint <= 0.0:
        slope[:] = 0.0
        return (0.0 if metric == "mi" else 1.0), total, slope
    p = histogram / total
    occupied = p > 0.0
    log_joint = np.log(p, where=occupied, out=np.zeros_like(p))
    fixed_marginal = p.sum(axis=1)
    log_fixed = np.log(fixed_marginal, where=fixed_marginal > 0.0, out=np.zeros_like(fixed_marginal))[:, None]
    if metric == "mi":
        value = (h_fixed + h_moving - h_joint) / np.log(log_base)
        derivative = (log_joint - log_fixed) / np.log(log_base)
    else:
        value = (h_fixed + h_moving) / h_joint
        derivative = (value * log_joint - log_fixed) / h_joint
    derivative[~occupied] = 0.0
    step = np.diff(derivative, axis=0) / total  # D[r + 1, c] - D[r, c] per unit of weight, rows 0 .. bins - 2
    lower, upper = np.zeros((bins, bins)), np.zeros((bins, bins))
    lower[:-1] = step  # indexed by the sample's cell (r, c): its lower moving bin c...
    upper[:-1, :-1] = step[:, 1:]  # ...and the bin c + 1 above it
    np.take(lower.ravel(), window._cell, out=slope)
    slope *= window.down
    np.take(upper.ravel(), window._cell, out=window._weights)
    window._weights *= window.up
    slope += window._weights
    slope *= window._valid
    return float(value), total, slope


def information_from_histogram(joint: np.ndarray, log_base: float = DEFAULT_LOG_BASE) -> tuple[float, float]:
    """Mutual information and normalised mutual information of a joint histogram.

    Parameters
    ----------
    joint : (B, B) array
        Joint histogram (counts or weights) of the fixed (rows) and moving
        (columns) intensities.
    log_base : float
        Base of the logarithm: 2 gives bits, e : nats.

    Returns
    -------
    mi : float
        MI(A, B) = H(A) + H(B) - H(A, B), 0 for an empty histogram.
    nmi : float
        NMI(A, B) = (H(A) + H(B)) / H(A, B), between 1 and 2; 1 for an empty
        or single-cell histogram.

    Notes
    -----
    With p the normalised joint histogram and p_A, p_B its marginals,
    H(A) = -sum p_A log p_A, H(B) likewise and H(A, B) = -sum p log p.
    MI is the paper's equation (5); NMI (Studholme et al.) does not reward a
    smaller overlap, which matters for partially overlapping images.

    References
    ----------
    .. [1] Paper, section 4, equation (5).
    .. [2] C. Studholme, D. L. G. Hill, D. J. Hawkes, "An overlap invariant
       entropy measure of 3D medical image alignment", Pattern Recognition
       32(1), 1999.
    """
    joint = np.asarray(joint, dtype=np.float64)
    if joint.ndim != 2 or joint.shape[0] != joint.shape[1]:
        raise ValueError(f"The joint histogram must be a square 2-D array; got shape {joint.shape}.")
    if log_base <= 0.0 or log_base == 1.0:
        raise ValueError(f"The log base must be positive and not 1; got {log_base}.")
    _, h_fixed, h_moving, h_joint = joint_entropies(joint)
    if h_joint <= 0.0:
        return 0.0, 1.0
    return float((h_fixed + h_moving - h_joint) / np.log(log_base)), float((h_fixed + h_moving) / h_joint)


def quantize(image: np.ndarray, bins: int, mask: np.ndarray | None = None) -> np.ndarray:
    """Scale an image linearly to [0, bins - 1] (float32), masked-out pixels to -1.

    The range is taken from the valid pixels; a constant image maps to 0.
    """
    if bins < 2:
        raise ValueError(f"MI needs at least 2 bins; got {bins}.")
    image = np.asarray(image, dtype=np.float32)
    valid = np.isfinite(image) if mask is None else (np.asarray(mask, dtype=bool) & np.isfinite(image))
    if not valid.any():
        return np.full(image.shape, -1.0, dtype=np.float32)
    low, high = float(image[valid].min()), float(image[valid].max())
    span = high - low if high > low else 1.0
    scaled = np.where(valid, (image - low) * ((bins - 1) / span), -1.0)
    return scaled.astype(np.float32)


def joint_histogram(
    fixed: np.ndarray, moving: np.ndarray, bins: int = DEFAULT_BINS, mask: np.ndarray | None = None
) -> np.ndarray:
    """Parzen-windowed (bilinear) joint histogram of two equally shaped images.

    Parameters
    ----------
    fixed, moving : array
        Images of the same shape; each is scaled linearly over its valid range.
    bins : int
        Number of intensity bins per image.
    mask : bool array, optional
        Pixels to use; non-finite pixels are always ignored.

    Returns
    -------
    (bins, bins) float64 array of summed weights, fixed intensity along rows.
    """
    fixed = np.asarray(fixed)
    moving = np.asarray(moving)
    if fixed.shape != moving.shape:
        raise ValueError(f"The images must have the same shape; got {fixed.shape} and {moving.shape}.")
    if mask is not None and np.shape(mask) != fixed.shape:
        raise ValueError(f"The mask must have the images' shape {fixed.shape}; got {np.shape(mask)}.")
    return quantized_joint_histogram(
        np.atleast_2d(quantize(fixed, bins, mask)), np.atleast_2d(quantize(moving, bins, mask)), bins
    )


def mutual_information(
    fixed: np.ndarray,
    moving: np.ndarray,
    bins: int = DEFAULT_BINS,
    log_base: float = DEFAULT_LOG_BASE,
    mask: np.ndarray | None = None,
) -> tuple[float, float]:
    """Mutual information and normalised mutual information of two aligned images.

    Parameters
    ----------
    fixed, moving : array
        Images of the same shape, sampled on the same pixel grid.
    bins : int
        Intensity bins per image of the Parzen-windowed joint histogram.
    log_base : float
        Logarithm base (2: bits).
    mask : bool array, optional
        Pixels to use.

    Returns
    -------
    mi, nmi : float
        See :func:`information_from_histogram`.

    Notes
    -----
    MI(A, B) = H(A) + H(B) - H(A, B) and NMI = (H(A) + H(B)) / H(A, B), with
    entropies of the bilinear-Parzen joint histogram described in the module
    docstring. MI grows with ``bins`` and depends on ``log_base``; report both.

    References
    ----------
    .. [1] Paper, section 4, equation (5).
    .. [2] F. Maes et al., "Multimodality image registration by maximization of
       mutual information", IEEE TMI 16(2), 1997 (partial-volume weighting).
    """
    return information_from_histogram(joint_histogram(fixed, moving, bins, mask), log_base)
