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


def gradient_epsilon(image: np.ndarray, valid: np.ndarray | None = None) -> float:
    """The edge-strength scale eps of an image: the 80th percentile of its gradient magnitude (central differences),
    over the pixels ``valid`` marks (every pixel by default)."""
    gx, gy = _central_gradients(np.asarray(image, dtype=np.float32))
    magnitude = np.hypot(gx, gy)[1:-1, 1:-1]
    if valid is not None and np.count_nonzero(valid[1:-1, 1:-1]):
        magnitude = magnitude[np.asarray(valid, dtype=bool)[1:-1, 1:-1]]
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


_NEIGHBOURS = np.array([[0, 1, 0], [1, 0, 1], [0, 1, 0]], np.uint8)  # the four neighbours of a pixel, for cv2.erode


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

    def __init__(self, moving_x: np.ndarray, moving_y: np.ndarray, canvas_shape: tuple[int, int],
                 moving_valid: np.ndarray | None = None) -> None:
        self.shape, self.canvas_shape = moving_x.shape, canvas_shape
        if canvas_shape[0] < self.shape[0] or canvas_shape[1] < self.shape[1]:
            raise ValueError(f"The canvas {canvas_shape} must be at least the moving field's shape {self.shape}.")
        self.dft_shape = (cv2.getOptimalDFTSize(canvas_shape[0]), cv2.getOptimalDFTSize(canvas_shape[1]))
        if moving_valid is not None:
            valid = np.asarray(moving_valid, dtype=np.float32)
            moving_x, moving_y = moving_x * valid, moving_y * valid
        mxx, mxy, myy = moving_x * moving_x, moving_x * moving_y, moving_y * moving_y
        self.tensor_spectra = [self.spectrum(component) for component in _tensor_components(mxx, mxy, myy)]
        self.power_spectrum = self.spectrum((mxx + myy) ** 2)
        self.valid_spectrum = None if moving_valid is None else self.spectrum(valid)

    def window_sums(self, image: np.ndarray, spectrum: np.ndarray | None = None) -> np.ndarray:
        """Sums of ``image`` over the moving pixels that have data, at every offset inside the canvas
        (``spectrum``: the image's :meth:`spectrum`, if already taken)."""
        if self.valid_spectrum is None:
            return _window_sums(image, self.shape)
        return self.correlate([self.spectrum(image) if spectrum is None else spectrum], [self.valid_spectrum])

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
        The moving (H, W) field, prepared for canvases of this shape; where it was given a mask of the
        moving pixels that have data, only those count.
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
    fixed power and the overlap are box sums, from integral images, or
    correlations with the moving mask.
    """
    if fixed_x.shape != template.canvas_shape:
        raise ValueError(f"The fixed field {fixed_x.shape} must have the template's canvas shape "
                         f"{template.canvas_shape}.")
    fxx, fxy, fyy = fixed_x * fixed_x, fixed_x * fixed_y, fixed_y * fixed_y
    numerator = template.correlate([template.spectrum(component) for component in _tensor_components(fxx, fxy, fyy)],
                                   template.tensor_spectra)
    valid_spectrum = template.spectrum(fixed_valid)  # taken once for the moving power and the overlap
    moving_power = template.correlate([valid_spectrum], [template.power_spectrum])
    fixed_power = template.window_sums((fxx + fyy) ** 2)
    overlap = template.window_sums(fixed_valid, valid_spectrum)
    denominator = np.sqrt(np.maximum(fixed_power, 0.0) * np.maximum(moving_power, 0.0))
    values = np.where(denominator > 0.0, numerator / np.where(denominator > 0.0, denominator, 1.0), 0.0)
    return np.where(overlap >= min_weight, values, -np.inf)


def _aligned_empty(shape: tuple[int, int]) -> np.ndarray:
    """An uninitialised float32 array starting on a 64-byte boundary.

    OpenCV's sums (through Intel IPP) group their terms by the address's alignment, so the same values in
    two arrays may sum to results a last bit apart; on aligned arrays every evaluation sums alike.
    """
    size = int(np.prod(shape))
    buffer = np.empty(size + 16, np.float32)
    start = (-buffer.ctypes.data % 64) // 4
    return buffer[start:start + size].reshape(shape)


class SampledFieldSimilarity:
    """S between the field of fixed images sampled on the moving grid and one moving field, with reused arrays.

    The moving field's terms are computed once; the work arrays of an evaluation are kept, since the
    refinement evaluates hundreds of samplings of a full image (see :func:`sampled_tensor_similarity`).
    The fixed field is taken from twice the central differences, d = 2 grad I, with 2 eps: the same
    n = d / sqrt(|d|^2 + 4 eps^2), two passes over the image fewer. Sums are OpenCV's, accumulated in
    double precision in one pass each (numpy's float64 sums of float32 arrays cast first, at five times
    the cost).
    """

    def __init__(self, epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray,
                 moving_valid: np.ndarray | None = None) -> None:
        self.twice_epsilon2 = (2 * np.float32(epsilon)) ** 2
        self.moving_x, self.moving_y = moving_x[1:-1, 1:-1], moving_y[1:-1, 1:-1]
        self._moving_valid = None if moving_valid is None else np.asarray(moving_valid, dtype=bool)[1:-1, 1:-1]
        if self._moving_valid is not None:
            self.moving_x, self.moving_y = self.moving_x * self._moving_valid, self.moving_y * self._moving_valid
        self.moving_size = moving_x.size if moving_valid is None else int(np.count_nonzero(moving_valid))
        moving_m = self.moving_x * self.moving_x + self.moving_y * self.moving_y
        shape = self.moving_x.shape
        self.moving_m2 = _aligned_empty(shape)
        np.multiply(moving_m, moving_m, out=self.moving_m2)
        self._whole_moving_power = cv2.sumElems(self.moving_m2)[0]
        self._work = [_aligned_empty(shape) for _ in range(4)]
        self._valid = np.empty(shape, bool)
        self._neighbour_minimum: np.ndarray | None = None  # the samples' erosion, of the samples' shape

    def _defined(self, samples: np.ndarray) -> np.ndarray:
        """Where all four neighbours of a field pixel were sampled inside (non-negative), in ``self._valid``.

        The least of the four neighbours is one erosion by the cross without its centre (a third of the time
        of numpy's minima of shifted views, whose rows are not contiguous).
        """
        if self._neighbour_minimum is None or self._neighbour_minimum.shape != samples.shape:
            self._neighbour_minimum = np.empty(samples.shape, np.float32)
        least = cv2.erode(samples, _NEIGHBOURS, dst=self._neighbour_minimum)
        return np.greater_equal(least[1:-1, 1:-1], 0.0, out=self._valid)

    def __call__(self, samples: np.ndarray) -> tuple[float, float]:
        """S and the number of pixels where the sampled field is defined (all four neighbours inside) and the
        moving image has data."""
        samples = np.asarray(samples, dtype=np.float32)
        dx, dy, magnitude2, weight = self._work
        inside = self._moving_valid is None and samples.min() >= 0.0  # then every field pixel counts: no mask needed
        valid = None if inside else self._defined(samples)
        if self._moving_valid is not None:
            np.logical_and(valid, self._moving_valid, out=valid)
        cv2.subtract(samples[1:-1, 2:], samples[1:-1, :-2], dst=dx)  # OpenCV's: a third of numpy's time on
        cv2.subtract(samples[2:, 1:-1], samples[:-2, 1:-1], dst=dy)  # these views, the same IEEE differences
        np.multiply(dx, dx, out=magnitude2)
        magnitude2 += np.multiply(dy, dy, out=weight)
        inverse_norm2 = np.divide(np.float32(1.0), np.add(magnitude2, self.twice_epsilon2, out=weight), out=weight)
        if valid is not None:
            np.multiply(inverse_norm2, valid, out=inverse_norm2)  # 0 where undefined
        dot = np.multiply(dx, self.moving_x, out=dx)
        dot += np.multiply(dy, self.moving_y, out=dy)
        if valid is None:
            count, moving_power = float(self.moving_m2.size), self._whole_moving_power
        else:
            count = float(np.count_nonzero(valid))
            moving_power = cv2.sumElems(np.multiply(self.moving_m2, valid, out=dy))[0]
        np.multiply(dot, dot, out=dot)
        numerator = cv2.sumElems(np.multiply(dot, inverse_norm2, out=dot))[0]
        fixed_power = cv2.norm(np.multiply(magnitude2, inverse_norm2, out=magnitude2), cv2.NORM_L2SQR)  # sum |n|^4
        if fixed_power <= 0.0 or moving_power <= 0.0:
            return 0.0, count
        return numerator / np.sqrt(fixed_power * moving_power), count


def sampled_tensor_similarity(
    samples: np.ndarray, epsilon: float, moving_x: np.ndarray, moving_y: np.ndarray
) -> tuple[float, float]:
    """S between the field of a fixed image sampled on the moving grid (negative = outside) and the moving field.

    Returns S and the number of pixels where the sampled field is defined
    (all four neighbours inside). :class:`SampledFieldSimilarity` keeps the
    moving terms and work arrays for repeated evaluations.
    """
    return SampledFieldSimilarity(epsilon, moving_x, moving_y)(samples)
