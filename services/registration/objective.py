"""The registration objective: MI or NMI of the fixed image resampled on the moving image's pixel grid.

Both images are quantised to [0, bins - 1] once (see
:func:`services.registration.mutual_information.quantize`); the fixed image is
then sampled at ``H @ u`` for every moving pixel ``u`` with bilinear
interpolation, and samples that touch the outside of the fixed image are
dropped, which handles partial overlap. The ``"ngf"`` metric compares the
normalised gradient fields of the sampled fixed image and of the moving image
instead (:mod:`services.registration.gradient_fields`).
"""

from __future__ import annotations

import cv2
import numpy as np

from services.registration.gradient_fields import SampledFieldSimilarity
from services.registration.mutual_information import MovingWindow, quantized_information

METRICS = ("mi", "nmi", "ngf")
OUTSIDE = -1.0e4  # far below 0, so any bilinear sample touching the outside comes out negative (invalid)
# (flags, border mode, border value) of the two warps: bicubic of the fixed image, bilinear with the outside marked
_CUBIC = (cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, cv2.BORDER_REPLICATE, 0.0)
_LINEAR = (cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, cv2.BORDER_CONSTANT, OUTSIDE)


def _is_affine(matrix: np.ndarray) -> bool:
    """Whether a 3x3 matrix's last row is exactly (0, 0, 1), as products of affine matrices keep it."""
    return matrix[2, 0] == 0.0 and matrix[2, 1] == 0.0 and matrix[2, 2] == 1.0


class FixedSampler:
    """Samples one fixed image on a ``width`` x ``height`` moving grid, again and again, into reused arrays.

    Each call returns the same array, overwritten: the refinement evaluates hundreds of matrices, and a new
    array of a full image for each cost more in page faults than the warp itself. See :func:`sample_fixed`.
    """

    def __init__(self, fixed: np.ndarray, width: int, height: int, cubic: bool = False) -> None:
        self.fixed, self.size, self.cubic = np.asarray(fixed, dtype=np.float32), (width, height), cubic
        self.samples = np.empty((height, width), np.float32)
        self._corners = np.array([[0.0, width - 1.0, 0.0, width - 1.0], [0.0, 0.0, height - 1.0, height - 1.0],
                                  [1.0, 1.0, 1.0, 1.0]])  # the grid's corner pixels, homogeneous
        if cubic:
            self._ring = self.fixed.copy()
            self._ring[[0, -1], :] = OUTSIDE  # a bilinear sample touching this ring or the outside has a 4 x 4
            self._ring[:, [0, -1]] = OUTSIDE  # support that is not wholly inside the image
            self._support = np.empty((height, width), np.float32)
            self._outside = np.empty((height, width), bool)

    def _warp(self, image: np.ndarray, matrix: np.ndarray, out: np.ndarray, cubic: bool, affine: bool) -> np.ndarray:
        flags, border, value = _CUBIC if cubic else _LINEAR  # positional: OpenCV parses keywords at some cost
        if affine:
            return cv2.warpAffine(image, matrix[:2], self.size, out, flags, border, value)
        return cv2.warpPerspective(image, matrix, self.size, out, flags, border, value)

    def _support_inside(self, matrix: np.ndarray, affine: bool) -> bool:
        """Whether every bicubic support lies wholly inside the fixed image, so the ring's warp would mark none.

        An affine map takes the grid's rectangle to a parallelogram: its four corners decide. They must map
        0.05 px inside the ring's inner edge, beyond OpenCV's 1/32 px quantisation of warp coordinates.
        """
        if not affine:
            return False
        corners = matrix[:2] @ self._corners
        (low_x, low_y), (high_x, high_y) = corners.min(axis=1).tolist(), corners.max(axis=1).tolist()
        fixed_height, fixed_width = self.fixed.shape
        margin = 1.05
        return (low_x >= margin and high_x <= fixed_width - 1 - margin
                and low_y >= margin and high_y <= fixed_height - 1 - margin)

    def __call__(self, matrix: np.ndarray) -> np.ndarray:
        affine = _is_affine(matrix)
        samples = self._warp(self.fixed, matrix, self.samples, self.cubic, affine)
        if self.cubic:
            np.maximum(samples, 0.0, out=samples)
            if not self._support_inside(matrix, affine):
                support = self._warp(self._ring, matrix, self._support, False, affine)
                np.copyto(samples, np.float32(OUTSIDE), where=np.less(support, 0.0, out=self._outside))
        return samples


def sample_fixed(fixed: np.ndarray, matrix: np.ndarray, width: int, height: int, cubic: bool = False) -> np.ndarray:
    """The fixed image sampled at ``matrix @ (x, y, 1)`` for each pixel of a ``width`` x ``height`` grid.

    Bilinear by default; pixels mapped (even partly) outside the fixed image are negative. With ``cubic``,
    bicubic (OpenCV's Keys kernel, a = -0.75) of an image that must be non-negative: negative where the 4 x 4
    support touches the outside, overshoots below 0 clipped to 0. A new array; :class:`FixedSampler` reuses one.

    Notes
    -----
    Bilinear interpolation at a fractional offset t is also a low-pass filter, of variance t (1 - t) per axis,
    so the sampled image is blurred by an amount that varies with the sub-pixel position (the interpolation
    artefact of Pluim et al., "Interpolation artefacts in mutual information-based image registration",
    CVIU 77(2), 2000); a bicubic kernel varies much less.
    """
    return FixedSampler(fixed, width, height, cubic)(matrix)


def information(
    fixed_samples: np.ndarray, moving: np.ndarray | MovingWindow, bins: int, log_base: float
) -> tuple[float, float, float]:
    """MI, NMI and the number of valid samples of two quantised, equally shaped images (or the moving window)."""
    return quantized_information(fixed_samples, moving, bins, log_base)


def score(
    fixed_samples: np.ndarray, moving: MovingWindow, bins: int, log_base: float, metric: str, min_overlap: float
) -> float:
    """The value to maximise: MI or NMI, or -inf when fewer than ``min_overlap`` of the moving pixels (those with
    data) overlap.

    ``moving`` is the moving image's :func:`services.registration.mutual_information.moving_window`.
    """
    mi, nmi, count = information(fixed_samples, moving, bins, log_base)
    if count < min_overlap * moving.valid_size:
        return -np.inf
    return mi if metric == "mi" else nmi


def field_score(fixed_samples: np.ndarray, similarity: SampledFieldSimilarity, min_overlap: float) -> float:
    """Normalised-gradient-field similarity of the sampled fixed image and the moving field, -inf below overlap."""
    value, count = similarity(fixed_samples)
    if count < min_overlap * similarity.moving_size:
        return -np.inf
    return value
