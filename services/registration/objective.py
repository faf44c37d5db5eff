"""The registration objective: MI or NMI of the fixed image resampled on the moving image's pixel grid.

Both images are quantised to [0, bins - 1] once (see
:func:`services.registration.mutual_information.quantize`); the fixed image is
then sampled at ``H @ u`` for every moving pixel ``u`` with bilinear
interpolation, and samples that touch the outside of the fixed image are
dropped, which handles partial overlap. The ``"ngf"`` metric compares the
normalised gradient fields of the sampled fixed image and of the moving image
instead (:mod:`services.registration.gradient_fields`). :class:`ParzenObjective` evaluates MI or NMI
with its analytic gradient in the matrix, for the quasi-Newton refinement.
"""

from __future__ import annotations

import cv2
import numpy as np

from services.registration.gradient_fields import sampled_tensor_similarity
from services.registration.mutual_information import MovingWindow, information_slope, moving_window, quantized_information

METRICS = ("mi", "nmi", "ngf")
OUTSIDE = -1.0e4  # far below 0, so any bilinear sample touching the outside comes out negative (invalid)


def sample_fixed(fixed: np.ndarray, matrix: np.ndarray, width: int, height: int, cubic: bool = False) -> np.ndarray:
    """The fixed image sampled at ``matrix @ (x, y, 1)`` for each pixel of a ``width`` x ``height`` grid.

    Bilinear by default; pixels mapped (even partly) outside the fixed image are negative. With ``cubic``,
    bicubic (OpenCV's Keys kernel, a = -0.75) of an image that must be non-negative: negative where the 4 x 4
    support touches the outside, overshoots below 0 clipped to 0.

    Notes
    -----
    Bilinear interpolation at a fractional offset t is also a low-pass filter, of variance t (1 - t) per axis,
    so the sampled image is blurred by an amount that varies with the sub-pixel position (the interpolation
    artefact of Pluim et al., "Interpolation artefacts in mutual information-based image registration",
    CVIU 77(2), 2000); a bicubic kernel varies much less.
    """
    if cubic:
        inner = np.array(fixed, dtype=np.float32)
        inner[[0, -1], :] = OUTSIDE  # a bilinear sample touching this ring or the outside has a 4 x 4 support
        inner[:, [0, -1]] = OUTSIDE  # that is not wholly inside the image
        support_inside = sample_fixed(inner, matrix, width, height) >= 0.0
        flags = cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP
        if np.allclose(matrix[2], [0.0, 0.0, 1.0]):
            values = cv2.warpAffine(fixed, matrix[:2], (width, height), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        else:
            values = cv2.warpPerspective(fixed, matrix, (width, height), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        return np.where(support_inside, np.maximum(values, 0.0), OUTSIDE).astype(np.float32)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    if np.allclose(matrix[2], [0.0, 0.0, 1.0]):
        return cv2.warpAffine(fixed, matrix[:2], (width, height), flags=flags,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=OUTSIDE)
    return cv2.warpPerspective(fixed, matrix, (width, height), flags=flags,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=OUTSIDE)


def information(
    fixed_samples: np.ndarray, moving: np.ndarray | MovingWindow, bins: int, log_base: float
) -> tuple[float, float, float]:
    """MI, NMI and the number of valid samples of two quantised, equally shaped images (or the moving window)."""
    return quantized_information(fixed_samples, moving, bins, log_base)


def score(
    fixed_samples: np.ndarray, moving: MovingWindow, bins: int, log_base: float, metric: str, min_overlap: float
) -> float:
    """The value to maximise: MI or NMI, or -inf when fewer than ``min_overlap`` of the moving pixels overlap.

    ``moving`` is the moving image's :func:`services.registration.mutual_information.moving_window`.
    """
    mi, nmi, count = information(fixed_samples, moving, bins, log_base)
    if count < min_overlap * moving.column.size:
        return -np.inf
    return mi if metric == "mi" else nmi


def field_score(
    fixed_samples: np.ndarray, fixed_epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray, min_overlap: float
) -> float:
    """Normalised-gradient-field similarity of the sampled fixed image and the moving field, -inf below overlap."""
    value, count = sampled_tensor_similarity(fixed_samples, fixed_epsilon, moving_x, moving_y)
    if count < min_overlap * moving_x.size:
        return -np.inf
    return value


class ParzenObjective:
    """MI or NMI of a fixed image sampled at ``matrix @ u`` over a moving image's pixels u, and its gradient.

    Parameters
    ----------
    fixed, moving : 2-D arrays
        Images scaled to [0, bins - 1] (:func:`services.registration.mutual_information.quantize`); the fixed
        one is sampled bilinearly (:func:`sample_fixed`), the moving one defines the grid.
    bins : int
        Bins per image.
    log_base : float
        Logarithm base of MI.
    metric : {"mi", "nmi"}
        The value.
    min_overlap : float
        Least fraction of the moving pixels that must overlap; the value is -inf below it.

    Notes
    -----
    For an affine matrix M, chain rule through the samples f_s = F(M u_s):

        d value / d M_rc = sum_s (d value / d f_s) (d F / d x_r)(M u_s) u_sc,   u_s = (x_s, y_s, 1),

    with d value / d f_s from :func:`services.registration.mutual_information.information_slope` and the
    image gradient of F by central differences, sampled bilinearly like F (as Mattes et al. and ITK take the
    gradient of the image, not of its interpolant, whose derivative jumps at every pixel edge). One evaluation
    with the gradient costs about one and a half histogram passes, where a finite-difference model of a
    similarity costs fifteen. Not thread-safe (the moving window's work arrays).
    """

    def __init__(self, fixed: np.ndarray, moving: np.ndarray, bins: int, log_base: float, metric: str,
                 min_overlap: float) -> None:
        if metric not in ("mi", "nmi"):
            raise ValueError(f"The Parzen objective is MI or NMI; got the metric {metric!r}.")
        self.fixed = np.ascontiguousarray(fixed, dtype=np.float32)
        self.fixed_dx = cv2.Sobel(self.fixed, cv2.CV_32F, 1, 0, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
        self.fixed_dy = cv2.Sobel(self.fixed, cv2.CV_32F, 0, 1, ksize=1, scale=0.5, borderType=cv2.BORDER_REPLICATE)
        self.height, self.width = np.shape(moving)
        self.window = moving_window(moving, bins)
        self.bins, self.log_base, self.metric = bins, log_base, metric
        self.min_weight = min_overlap * self.window.column.size
        rows, columns = np.mgrid[0:self.height, 0:self.width]
        self._pixels = np.stack([columns.ravel(), rows.ravel(), np.ones(rows.size)]).astype(np.float64)
        self._samples = np.empty((self.height, self.width), np.float32)
        self._dx = np.empty((self.height, self.width), np.float32)
        self._dy = np.empty((self.height, self.width), np.float32)
        self._product = np.empty(rows.size, np.float64)

    def _warp(self, image: np.ndarray, matrix: np.ndarray, out: np.ndarray, outside: float) -> np.ndarray:
        return cv2.warpAffine(image, matrix[:2], (self.width, self.height), dst=out,
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=outside)

    def value(self, matrix: np.ndarray) -> float:
        """The value at any matrix (perspective ones too); -inf below the minimum overlap."""
        if np.allclose(matrix[2], [0.0, 0.0, 1.0]):
            samples = self._warp(self.fixed, matrix, self._samples, OUTSIDE)
        else:
            samples = sample_fixed(self.fixed, matrix, self.width, self.height)
        value, weight, _ = information_slope(samples, self.window, self.bins, self.log_base, self.metric)
        return value if weight >= self.min_weight else -np.inf

    def value_and_gradient(self, matrix: np.ndarray) -> tuple[float, np.ndarray]:
        """The value and its gradient in the top two rows of an affine ``matrix``, (2, 3); -inf below overlap."""
        if not np.allclose(matrix[2], [0.0, 0.0, 1.0]):
            raise ValueError("The analytic gradient is for affine matrices (last row 0, 0, 1).")
        samples = self._warp(self.fixed, matrix, self._samples, OUTSIDE)
        value, weight, slope = information_slope(samples, self.window, self.bins, self.log_base, self.metric)
        if weight < self.min_weight:
            return -np.inf, np.zeros((2, 3))
        gradient = np.empty((2, 3))
        for row, image, out in ((0, self.fixed_dx, self._dx), (1, self.fixed_dy, self._dy)):
            np.multiply(slope, self._warp(image, matrix, out, 0.0).ravel(), out=self._product)
            gradient[row] = self._pixels @ self._product
        return value, gradient
