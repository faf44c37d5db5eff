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


def _tensor_components(xx: np.ndarray, xy: np.ndarray, yy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The structure tensor's components weighted so that their products sum to (n_a . n_b)^2."""
    return xx, np.float32(np.sqrt(2.0)) * xy, yy


class FieldTemplate:
    """A moving field's structure tensor, transformed once for correlation with canvases of one shape.

    ``cv2.matchTemplate`` would transform the template again on every call; the coarse search correlates
    the same moving field with a canvas for each rotation and scale, so its spectra are kept here.
    """

    def __init__(self, moving_x: np.ndarray, moving_y: np.ndarray, canvas_shape: tuple[int, int]) -> None:
        self.shape, self.canvas_shape = moving_x.shape, canvas_shape
        if canvas_shape[0] < self.shape[0] or canvas_shape[1] < self.shape[1]:
            raise ValueError(f"The canvas {canvas_shape} must be at least the moving field's shape {self.shape}.")
        self.dft_shape = (cv2.getOptimalDFTSize(canvas_shape[0]), cv2.getOptimalDFTSize(canvas_shape[1]))
        mxx, mxy, myy = moving_x * moving_x, moving_x * moving_y, moving_y * moving_y
        self.tensor_spectra = [self.spectrum(component) for component in _tensor_components(mxx, mxy, myy)]
        self.power_spectrum = self.spectrum((mxx + myy) ** 2)

    def spectrum(self, image: np.ndarray) -> np.ndarray:
        """The packed real DFT of ``image`` zero-padded to the DFT size."""
        padded = np.zeros(self.dft_shape, np.float32)
        padded[:image.shape[0], :image.shape[1]] = image
        return cv2.dft(padded)

    def correlate(self, spectra: list[np.ndarray], templates: list[np.ndarray]) -> np.ndarray:
        """sum_k (canvas_k correlated with template_k) at every offset that keeps the template inside the canvas.

        A circular correlation over a DFT at least the canvas' size wraps only at offsets outside that range.
        """
        product = sum(cv2.mulSpectrums(spectrum, template, 0, conjB=True)
                      for spectrum, template in zip(spectra, templates))
        full = cv2.dft(product, flags=cv2.DFT_INVERSE | cv2.DFT_SCALE | cv2.DFT_REAL_OUTPUT)
        return full[:self.canvas_shape[0] - self.shape[0] + 1, :self.canvas_shape[1] - self.shape[1] + 1]


def tensor_similarity_map(
    fixed_x: np.ndarray, fixed_y: np.ndarray, fixed_valid: np.ndarray, template: FieldTemplate, min_weight: float,
) -> np.ndarray:
    """Tensor similarity S of the moving field against every integer offset of a larger fixed field.

    Parameters
    ----------
    fixed_x, fixed_y : (H + 2m, W + 2m) float32 arrays
        Fixed field on a canvas of the moving grid widened by m on each side.
    fixed_valid : same shape, float32
        1 where the fixed field is defined, else 0 (the field is 0 there too).
    template : FieldTemplate
        The moving (H, W) field, prepared for canvases of this shape.
    min_weight : float
        Least number of overlapping pixels; offsets with fewer get -inf.

    Returns
    -------
    (2m + 1, 2m + 1) array; entry (dy, dx) compares moving pixel u with
    canvas pixel u + (dx, dy).

    Notes
    -----
    The numerator sum_u (n_m . n_f)^2 = sum_u n_m n_m^T : n_f n_f^T and the
    moving power are correlations, computed by the convolution theorem; the
    fixed power and the overlap are box sums, from integral images.
    """
    if fixed_x.shape != template.canvas_shape:
        raise ValueError(f"The fixed field {fixed_x.shape} must have the template's canvas shape "
                         f"{template.canvas_shape}.")
    fxx, fxy, fyy = fixed_x * fixed_x, fixed_x * fixed_y, fixed_y * fixed_y
    numerator = template.correlate([template.spectrum(component) for component in _tensor_components(fxx, fxy, fyy)],
                                   template.tensor_spectra)
    moving_power = template.correlate([template.spectrum(fixed_valid)], [template.power_spectrum])
    fixed_power = _window_sums((fxx + fyy) ** 2, template.shape)
    overlap = _window_sums(fixed_valid, template.shape)
    denominator = np.sqrt(np.maximum(fixed_power, 0.0) * np.maximum(moving_power, 0.0))
    values = np.where(denominator > 0.0, numerator / np.where(denominator > 0.0, denominator, 1.0), 0.0)
    return np.where(overlap >= min_weight, values, -np.inf)


class SampledFieldSimilarity:
    """S between the field of fixed images sampled on the moving grid and one moving field, with reused arrays.

    The moving field's terms are computed once; the work arrays of an evaluation are kept, since the
    refinement evaluates hundreds of samplings of a full image (see :func:`sampled_tensor_similarity`).
    """

    def __init__(self, epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray) -> None:
        self.epsilon2 = np.float32(epsilon) ** 2
        self.moving_size = moving_x.size
        self.moving_x, self.moving_y = moving_x[1:-1, 1:-1], moving_y[1:-1, 1:-1]
        moving_m = self.moving_x * self.moving_x + self.moving_y * self.moving_y
        self.moving_m2 = moving_m * moving_m
        self._whole_moving_power = float(self.moving_m2.sum(dtype=np.float64))  # the sum below, every weight 1
        shape = self.moving_x.shape
        self._work = [np.empty(shape, np.float32) for _ in range(5)]
        self._valid = np.empty(shape, bool)

    def __call__(self, samples: np.ndarray) -> tuple[float, float]:
        """S and the number of pixels where the sampled field is defined (all four neighbours inside)."""
        left, right = samples[1:-1, :-2], samples[1:-1, 2:]
        up, down = samples[:-2, 1:-1], samples[2:, 1:-1]
        gx, gy, first, second, product = self._work
        inside = samples.min() >= 0.0  # then every field pixel is defined: the mask's passes are skipped
        if not inside:
            np.minimum(left, right, out=first)
            np.minimum(up, down, out=second)
            np.minimum(first, second, out=first)
            valid = np.greater_equal(first, 0.0, out=self._valid)
            weight = second
            np.copyto(weight, valid)
        np.multiply(np.subtract(right, left, out=gx), np.float32(0.5), out=gx)
        np.multiply(np.subtract(down, up, out=gy), np.float32(0.5), out=gy)
        magnitude2 = np.multiply(gx, gx, out=first)
        magnitude2 += np.multiply(gy, gy, out=product)
        np.add(magnitude2, self.epsilon2, out=product)
        if inside:
            inverse_norm2 = np.divide(np.float32(1.0), product, out=second)
            count, moving_power = float(self.moving_m2.size), self._whole_moving_power
        else:
            inverse_norm2 = np.divide(weight, product, out=weight)  # 0 outside
            count = float(np.count_nonzero(valid))
            moving_power = _weighted_sum(self.moving_m2, valid, product)
        dot = np.multiply(gx, self.moving_x, out=gx)
        dot += np.multiply(gy, self.moving_y, out=gy)
        numerator = _weighted_sum(np.multiply(dot, dot, out=dot), inverse_norm2, product)
        np.multiply(magnitude2, magnitude2, out=magnitude2)
        fixed_power = _weighted_sum(magnitude2, np.multiply(inverse_norm2, inverse_norm2, out=inverse_norm2), product)
        if fixed_power <= 0.0 or moving_power <= 0.0:
            return 0.0, count
        return numerator / np.sqrt(fixed_power * moving_power), count


def _weighted_sum(values: np.ndarray, weights: np.ndarray, out: np.ndarray) -> float:
    """sum values * weights in float64, the products written into ``out`` (not np.vdot: BLAS threads spin)."""
    return float(np.multiply(values, weights, out=out).sum(dtype=np.float64))


def sampled_tensor_similarity(
    samples: np.ndarray, epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray
) -> tuple[float, float]:
    """S between the field of a fixed image sampled on the moving grid (negative = outside) and the moving field.

    Returns S and the number of pixels where the sampled field is defined
    (all four neighbours inside). :class:`SampledFieldSimilarity` keeps the
    moving terms and work arrays for repeated evaluations.
    """
    return SampledFieldSimilarity(epsilon, moving_x, moving_y)(samples)
