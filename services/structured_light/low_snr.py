"""Refinement of projector coordinates where the projected signal is weak (grazing light, dark albedo)."""

from __future__ import annotations

import numba
import numpy as np

_MIN_NEIGHBOURS = 6
_OUTLIER_SIGMAS = 4.0
_NOISE_SAMPLES = 30_000  # a median over this many pixels, on a regular grid, is as good as over all


def phase_noise_scale(steps: int, period: float, camera_noise: float) -> float:
    """Standard deviation, in projector pixels, of an N-step phase-shift coordinate times its modulation.

    Notes
    -----
    With intensity noise sigma_I and modulation B, N-step phase shifting gives
    sigma_phi = sigma_I sqrt(2 / N) / B, so sigma_x = P sigma_phi / (2 pi) = scale / B with
    scale = P sigma_I sqrt(2 / N) / (2 pi) [1]_.

    References
    ----------
    .. [1] C. Zuo et al., "Phase shifting algorithms for fringe projection profilometry: a review",
       Optics and Lasers in Engineering 109, 2018, section 5.
    """
    return float(period / (2 * np.pi) * camera_noise * np.sqrt(2.0 / steps))


def estimate_camera_noise(modulation: np.ndarray, quality: np.ndarray, steps: int) -> float:
    """Camera noise (grey levels) from the residuals of the per-pixel sinusoid fits.

    Notes
    -----
    A pixel's fitted AC energy is N B^2 / 2 and ``quality`` q is its share of the total AC energy, so
    the residual energy is N B^2 (1 - q) / (2 q), spread over N - 3 degrees of freedom. The median over
    about 30,000 pixels on a regular grid is robust to edges and motion.
    """
    if steps <= 3:
        raise ValueError("Estimating the camera noise needs more than 3 phase steps.")
    step = max(1, int(np.sqrt(modulation.size / _NOISE_SAMPLES)))
    modulation, quality = modulation[::step, ::step].ravel(), quality[::step, ::step].ravel()
    usable = np.isfinite(modulation) & np.isfinite(quality) & (quality > 0) & (modulation > 0)
    if not usable.any():
        raise ValueError("No pixel has a usable sinusoid fit to estimate the camera noise from.")
    b, q = modulation[usable].astype(np.float64), quality[usable].astype(np.float64)
    return float(np.sqrt(np.median(steps * b**2 * (1 - q) / (2 * q * (steps - 3)))))


@numba.njit(cache=True, inline="always")
def _median_in_place(values, n):
    """Median of values[:n], sorting them in place: an insertion sort of at most 25 values costs less
    than the copy that ``np.median`` allocates per call."""
    for i in range(1, n):
        value = values[i]
        j = i - 1
        while j >= 0 and values[j] > value:
            values[j + 1] = values[j]
            j -= 1
        values[j + 1] = value
    return values[n // 2] if n % 2 else 0.5 * (values[n // 2 - 1] + values[n // 2])


@numba.njit(cache=True, inline="always")
def _median_neighbour_differences(coordinates, row, col, radius, buffer):
    """The window's median coordinate differences between horizontal and between vertical neighbours."""
    height, width = coordinates.shape
    m = 0
    for r in range(max(0, row - radius), min(height, row + radius + 1)):
        for c in range(max(0, col - radius), min(width - 1, col + radius)):
            if np.isfinite(coordinates[r, c]) and np.isfinite(coordinates[r, c + 1]):
                buffer[m] = coordinates[r, c + 1] - coordinates[r, c]
                m += 1
    slope_x = _median_in_place(buffer, m) if m > 0 else 0.0
    m = 0
    for r in range(max(0, row - radius), min(height - 1, row + radius)):
        for c in range(max(0, col - radius), min(width, col + radius + 1)):
            if np.isfinite(coordinates[r, c]) and np.isfinite(coordinates[r + 1, c]):
                buffer[m] = coordinates[r + 1, c] - coordinates[r, c]
                m += 1
    slope_y = _median_in_place(buffer, m) if m > 0 else 0.0
    return slope_x, slope_y


# Hand-written with numba: a robust weighted plane fit per weak pixel has no vectorised library form.
@numba.njit(parallel=True, cache=True)
def _refine_kernel(coordinates, modulation, noise_scale, threshold, radius, max_step, out):
    height, width = coordinates.shape
    window = (2 * radius + 1) ** 2
    for row in numba.prange(height):
        values = np.empty(window, dtype=np.float32)
        ordered = np.empty(window, dtype=np.float32)
        differences = np.empty(window, dtype=np.float32)
        dxs = np.empty(window)
        dys = np.empty(window)
        ws = np.empty(window)
        trend = np.empty(window)
        for col in range(width):
            centre = coordinates[row, col]
            out[row, col] = centre
            sigma = noise_scale / modulation[row, col]  # NaN modulation: not refined
            if not (np.isfinite(centre) and sigma > threshold):
                continue
            n = 0
            lowest, highest = np.inf, -np.inf
            for r in range(max(0, row - radius), min(height, row + radius + 1)):
                for c in range(max(0, col - radius), min(width, col + radius + 1)):
                    value = coordinates[r, c]
                    if np.isfinite(value):
                        values[n] = value
                        dxs[n] = c - col
                        dys[n] = r - row
                        ws[n] = modulation[r, c] * modulation[r, c] if np.isfinite(modulation[r, c]) else 0.0
                        ordered[n] = value
                        lowest, highest = min(lowest, value), max(highest, value)
                        n += 1
            # Decoding errors jump by a period from the locally linear field. First the plain test against the
            # window's median; where it leaves too few neighbours or calls the pixel an outlier (a steep or
            # curved field at a limb changes by more than max_step across the window), the detrended one.
            for i in range(n):
                trend[i] = 0.0
            # In a window spanning at most max_step every value passes whatever the median: skip sorting.
            median = _median_in_place(ordered, n) if highest - lowest > max_step else lowest
            for detrended in (False, True):
                if detrended:
                    slope_x, slope_y = _median_neighbour_differences(coordinates, row, col, radius, differences)
                    for i in range(n):
                        trend[i] = slope_x * dxs[i] + slope_y * dys[i]
                        ordered[i] = values[i] - trend[i]
                    median = _median_in_place(ordered, n)
                s00 = s01 = s02 = s11 = s12 = s22 = b0 = b1 = b2 = 0.0
                kept = 0
                for i in range(n):
                    if abs(values[i] - trend[i] - median) > max_step:
                        continue
                    w, x, y, v = ws[i], dxs[i], dys[i], values[i]
                    s00 += w
                    s01 += w * x
                    s02 += w * y
                    s11 += w * x * x
                    s12 += w * x * y
                    s22 += w * y * y
                    b0 += w * v
                    b1 += w * x * v
                    b2 += w * y * v
                    kept += 1
                determinant = (s00 * (s11 * s22 - s12 * s12) - s01 * (s01 * s22 - s12 * s02)
                               + s02 * (s01 * s12 - s11 * s02))
                out[row, col] = np.nan
                if kept < _MIN_NEIGHBOURS or not determinant > 0.0:
                    continue
                intercept = (b0 * (s11 * s22 - s12 * s12) - s01 * (b1 * s22 - s12 * b2)
                             + s02 * (b1 * s12 - s11 * b2)) / determinant
                # The outlier test's sigma, scaled by the fit's reduced chi-square when the plane misfits (a
                # curved coordinate field at a limb), so that model error is not taken for a decoding error.
                inflation = 1.0
                if detrended and kept > 3:
                    slope_u = (s00 * (b1 * s22 - s12 * b2) - b0 * (s01 * s22 - s12 * s02)
                               + s02 * (s01 * b2 - b1 * s02)) / determinant
                    slope_v = (s00 * (s11 * b2 - b1 * s12) - s01 * (s01 * b2 - b1 * s02)
                               + b0 * (s01 * s12 - s11 * s02)) / determinant
                    chi_square = 0.0
                    for i in range(n):
                        if abs(values[i] - trend[i] - median) <= max_step:
                            residual = values[i] - intercept - slope_u * dxs[i] - slope_v * dys[i]
                            chi_square += ws[i] * residual * residual
                    reduced = chi_square / (noise_scale * noise_scale * (kept - 3))
                    if reduced > 1.0:
                        inflation = np.sqrt(reduced)
                if abs(centre - intercept) <= _OUTLIER_SIGMAS * sigma * inflation:
                    out[row, col] = intercept
                    break


def refine_low_snr(coordinates: np.ndarray, modulation: np.ndarray, noise_scale: float, *,
                   threshold: float = 0.1, radius: int = 2, max_step: float = 4.0) -> np.ndarray:
    """Replace noisy projector coordinates by a robust, inverse-variance weighted local plane fit.

    Parameters
    ----------
    coordinates : (H, W) float array
        Decoded projector coordinates, NaN where invalid.
    modulation : (H, W) float array
        Signal amplitude B per pixel; the fit weights are B^2 (inverse phase variance).
    noise_scale : float
        Predicted coordinate noise times modulation (:func:`phase_noise_scale`): a pixel's noise is
        ``noise_scale / B`` projector pixels.
    threshold : float
        Only pixels noisier than this many projector pixels are refined; the rest are returned unchanged.
    radius : int
        Half-size of the square window.
    max_step : float
        Neighbours further than this from the window median (a decoding error) are left out of the fit.

    Returns
    -------
    refined : (H, W) float32 array
        The coordinates, refined where noisy; NaN where a noisy pixel has fewer than 6 consistent
        neighbours (within ``max_step`` of the window's median after removing the median neighbour
        differences, so that a steep coordinate field keeps them) or lies more than 4 sigma from its
        neighbourhood's fit (an outlier), sigma scaled by the square root of the fit's reduced chi-square
        where that exceeds 1 (the plane does not describe a curved field within the window).

    Notes
    -----
    Fits x(u, v) = a + b (u - u0) + c (v - v0) by weighted least squares over the window and keeps a.
    For a locally linear coordinate field the estimate is unbiased whatever the weights, so the one-sided
    windows at a terminator, where B falls toward zero, do not pull it; with n neighbours its variance is
    about sigma^2 / n. This is local polynomial regression (a weighted Savitzky-Golay filter) [1]_.

    References
    ----------
    .. [1] W. S. Cleveland, S. J. Devlin, "Locally weighted regression", Journal of the American
       Statistical Association 83(403), 1988.
    """
    if coordinates.shape != modulation.shape:
        raise ValueError("coordinates and modulation must have the same shape.")
    if radius < 1:
        raise ValueError(f"The window radius must be at least 1 pixel; got {radius}.")
    refined = np.empty(coordinates.shape, dtype=np.float32)
    _refine_kernel(np.ascontiguousarray(coordinates, dtype=np.float32), np.ascontiguousarray(modulation, dtype=np.float32),
                   float(noise_scale), float(threshold), int(radius), float(max_step), refined)
    return refined
