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

from services.registration.gradient_fields import sampled_tensor_similarity
from services.registration.mutual_information import MovingWindow, quantized_information

METRICS = ("mi", "nmi", "ngf")
OUTSIDE = -1.0e4  # far below 0, so any bilinear sample touching the outside comes out negative (invalid)


def _is_affine(matrix: np.ndarray) -> bool:
    """Whether a 3x3 matrix's last row is exactly (0, 0, 1), as products of affine matrices keep it."""
    return matrix[2, 0] == 0.0 and matrix[2, 1] == 0.0 and matrix[2, 2] == 1.0


def sample_fixed(fixed: np.ndarray, matrix: np.ndarray, width: int, height: int, cubic: bool = False,
                 out: np.ndarray | None = None) -> np.ndarray:
    """The fixed image sampled at ``matrix @ (x, y, 1)`` for each pixel of a ``width`` x ``height`` grid.

    Bilinear by default; pixels mapped (even partly) outside the fixed image are negative. With ``cubic``,
    bicubic (OpenCV's Keys kernel, a = -0.75) of an image that must be non-negative: negative where the 4 x 4
    support touches the outside, overshoots below 0 clipped to 0. A bilinear sampling may write into ``out``, a
    (height, width) float32 array (the refinement reuses one: a new array of a full image for each of its
    hundreds of evaluations cost more in page faults than the warp itself).

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
        if _is_affine(matrix):
            values = cv2.warpAffine(fixed, matrix[:2], (width, height), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        else:
            values = cv2.warpPerspective(fixed, matrix, (width, height), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        return np.where(support_inside, np.maximum(values, 0.0), OUTSIDE).astype(np.float32)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    if _is_affine(matrix):
        return cv2.warpAffine(fixed, matrix[:2], (width, height), dst=out, flags=flags,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=OUTSIDE)
    return cv2.warpPerspective(fixed, matrix, (width, height), dst=out, flags=flags,
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
    if count < min_overlap * moving.level_offset.size:
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
