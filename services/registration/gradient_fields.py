"""Normalised gradient fields: a multimodal similarity from the alignment of edge directions.

Infrared and visible images of one scene share where their edges are and
which way they run, not their grey levels, nor even the sign of their
contrast (a hot part may be darker or brighter than its surroundings in the
visible band). The normalised gradient field n = grad I / sqrt(|grad I|^2 +
eps^2) is a unit vector on edges and fades to zero on flat, noisy ground
(eps sets the edge strength that counts). The similarity of two fields is
the normalised correlation of their structure tensors n n^T,

    S = sum_u (n_m . n_f)^2 / sqrt(sum_u |n_m|^4 * sum_u |n_f|^4),

over the pixels u where both are defined: 1 when every edge runs the same
way in both images, insensitive to contrast polarity, and, being a sum of
products, computable for every integer shift at once by correlation, which
the coarse search uses.
"""

from __future__ import annotations

import cv2
import numpy as np

_EPSILON_PERCENTILE = 80.0  # eps = this percentile of |grad I|: the strongest fifth of the edges count fully


def _central_gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central differences; the outer rows and columns, which have no two neighbours, are zero."""
    gx = np.zeros_like(image, dtype=np.float32)
    gy = np.zeros_like(image, dtype=np.float32)
    gx[:, 1:-1] = 0.5 * (image[:, 2:] - image[:, :-2])
    gy[1:-1, :] = 0.5 * (image[2:, :] - image[:-2, :])
    return gx, gy


def gradient_epsilon(image: np.ndarray) -> float:
    """The edge-strength scale eps of an image: the 80th percentile of its gradient magnitude (central differences)."""
    gx, gy = _central_gradients(np.asarray(image, dtype=np.float32))
    magnitude = np.hypot(gx, gy)[1:-1, 1:-1]
    epsilon = float(np.percentile(magnitude, _EPSILON_PERCENTILE))
    return epsilon if epsilon > 0.0 else float(magnitude.max()) or 1.0


def normalized_gradient_field(image: np.ndarray, epsilon: float) -> tuple[np.ndarray, np.ndarray]:
    """The field n = grad I / sqrt(|grad I|^2 + eps^2) of a 2-D image, as two float32 images (x and y components).

    Parameters
    ----------
    image : 2-D array
        Grey image, already smoothed to the scale of interest.
    epsilon : float
        Edge-strength scale, in grey levels per pixel; see :func:`gradient_epsilon`.

    Returns
    -------
    nx, ny : 2-D float32 arrays
        Components of n; zero on the outer rows and columns.

    References
    ----------
    .. [1] E. Haber, J. Modersitzki, "Intensity gradient based registration and
       fusion of multi-modal images", MICCAI 2006, LNCS 4191.
    """
    if not epsilon > 0.0:
        raise ValueError(f"The gradient-field epsilon must be positive; got {epsilon}.")
    gx, gy = _central_gradients(np.asarray(image, dtype=np.float32))
    norm = np.sqrt(gx * gx + gy * gy + np.float32(epsilon) ** 2)
    return gx / norm, gy / norm


def _window_sums(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Sums of ``image`` over every ``shape``-sized window (the correlation with a box), from its integral image."""
    height, width = shape
    total = cv2.integral(image, sdepth=cv2.CV_64F)
    return (total[height:, width:] - total[:-height, width:] - total[height:, :-width] + total[:-height, :-width])


def tensor_similarity_map(
    fixed_x: np.ndarray, fixed_y: np.ndarray, fixed_valid: np.ndarray, moving_x: np.ndarray, moving_y: np.ndarray,
    min_weight: float,
) -> np.ndarray:
    """Tensor similarity S of the moving field against every integer offset of a larger fixed field.

    Parameters
    ----------
    fixed_x, fixed_y : (H + 2m, W + 2m) float32 arrays
        Fixed field on a canvas of the moving grid widened by m on each side.
    fixed_valid : same shape, float32
        1 where the fixed field is defined, else 0 (the field is 0 there too).
    moving_x, moving_y : (H, W) float32 arrays
        Moving field.
    min_weight : float
        Least number of overlapping pixels; offsets with fewer get -inf.

    Returns
    -------
    (2m + 1, 2m + 1) array; entry (dy, dx) compares moving pixel u with
    canvas pixel u + (dx, dy).
    """
    fxx, fxy, fyy = fixed_x * fixed_x, fixed_x * fixed_y, fixed_y * fixed_y
    mxx, mxy, myy = moving_x * moving_x, moving_x * moving_y, moving_y * moving_y
    # n_m . n_f squared summed over the three tensor components at once: matchTemplate sums over channels
    root2 = np.float32(np.sqrt(2.0))
    numerator = cv2.matchTemplate(cv2.merge([fxx, root2 * fxy, fyy]), cv2.merge([mxx, root2 * mxy, myy]),
                                  cv2.TM_CCORR)
    fixed_power = _window_sums((fxx + fyy) ** 2, moving_x.shape)
    moving_power = cv2.matchTemplate(fixed_valid, (mxx + myy) ** 2, cv2.TM_CCORR)
    overlap = _window_sums(fixed_valid, moving_x.shape)
    denominator = np.sqrt(np.maximum(fixed_power, 0.0) * np.maximum(moving_power, 0.0))
    values = np.where(denominator > 0.0, numerator / np.where(denominator > 0.0, denominator, 1.0), 0.0)
    return np.where(overlap >= min_weight, values, -np.inf)


def _weighted_sum(values: np.ndarray, weights: np.ndarray) -> float:
    """sum values * weights in float64 (not np.vdot: BLAS threads spin on this shared machine)."""
    return float(np.multiply(values, weights).sum(dtype=np.float64))


def sampled_tensor_similarity(
    samples: np.ndarray, epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray
) -> tuple[float, float]:
    """S between the field of a fixed image sampled on the moving grid (negative = outside) and the moving field.

    Returns S and the number of pixels where the sampled field is defined
    (all four neighbours inside).
    """
    left, right = samples[1:-1, :-2], samples[1:-1, 2:]
    up, down = samples[:-2, 1:-1], samples[2:, 1:-1]
    valid = (np.minimum(np.minimum(left, right), np.minimum(up, down)) >= 0.0).astype(np.float32)
    gx, gy = 0.5 * (right - left), 0.5 * (down - up)
    magnitude2 = gx * gx + gy * gy
    inverse_norm2 = valid / (magnitude2 + np.float32(epsilon) ** 2)
    mx, my = moving_x[1:-1, 1:-1], moving_y[1:-1, 1:-1]
    dot = gx * mx + gy * my
    numerator = _weighted_sum(dot * dot, inverse_norm2)
    fixed_power = _weighted_sum(magnitude2 * magnitude2, inverse_norm2 * inverse_norm2)
    moving_m = mx * mx + my * my
    moving_power = _weighted_sum(moving_m * moving_m, valid)
    count = float(valid.sum())
    if fixed_power <= 0.0 or moving_power <= 0.0:
        return 0.0, count
    return numerator / np.sqrt(fixed_power * moving_power), count
