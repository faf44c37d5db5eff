"""Refinement of projector coordinates where the projected signal is weak (grazing light, dark albedo)."""

from __future__ import annotations

import cv2
import numpy as np

from services.structured_light.row_bands import map_bands

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


def _finite_medians(values: np.ndarray, default: float = np.nan) -> np.ndarray:
    """Median of the finite values of each row (the mean of the middle two for an even count); ``default``
    for a row without one. Sorting puts NaN last, so the finite values lead each sorted row."""
    ordered = np.sort(values, axis=1)
    count = np.count_nonzero(np.isfinite(ordered), axis=1)
    rows = np.arange(len(values))
    upper = ordered[rows, np.minimum(count // 2, values.shape[1] - 1)].astype(np.float64)
    lower = ordered[rows, np.maximum(count - 1, 0) // 2].astype(np.float64)
    return np.where(count > 0, 0.5 * (lower + upper), default)


def _neighbour_difference_medians(padded: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                                  radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the window's median coordinate differences between horizontal and between vertical
    neighbours (0 where there are none), from the NaN-padded coordinates."""
    size = 2 * radius + 1
    window = np.lib.stride_tricks.sliding_window_view(padded, (size, size))[rows, cols]
    horizontal = (window[:, :, 1:] - window[:, :, :-1]).reshape(len(rows), -1)
    vertical = (window[:, 1:, :] - window[:, :-1, :]).reshape(len(rows), -1)
    return _finite_medians(horizontal, 0.0), _finite_medians(vertical, 0.0)


def _row_moments(rows: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """rows @ basis.T by OpenCV: numpy hands it to the multithreaded BLAS, which on a busy machine spins its
    threads for tens of times the work (see ``services.geometry.rigid``)."""
    return cv2.transform(np.ascontiguousarray(rows).reshape(len(rows), 1, -1), basis).reshape(len(rows), -1)


def _plane_fits(values, weights, dx, dy, kept):
    """Weighted least-squares planes v = a + b dx + c dy through each row's ``kept`` values: the
    intercepts a, the slopes b and c, and the determinant of the normal equations (0 or less: no fit)."""
    w = np.where(kept, weights, 0.0)
    v = np.where(kept, values, 0.0)
    s00, s01, s02, s11, s12, s22 = _row_moments(w, np.stack([np.ones_like(dx), dx, dy, dx * dx, dx * dy, dy * dy])).T
    b0, b1, b2 = _row_moments(w * v, np.stack([np.ones_like(dx), dx, dy])).T
    m00, m01, m02 = s11 * s22 - s12 * s12, s01 * s22 - s12 * s02, s01 * s12 - s11 * s02
    determinant = s00 * m00 - s01 * m01 + s02 * m02
    with np.errstate(divide="ignore", invalid="ignore"):
        intercept = (b0 * m00 - s01 * (b1 * s22 - s12 * b2) + s02 * (b1 * s12 - s11 * b2)) / determinant
        slope_u = (s00 * (b1 * s22 - s12 * b2) - b0 * m01 + s02 * (s01 * b2 - b1 * s02)) / determinant
        slope_v = (s00 * (s11 * b2 - b1 * s12) - s01 * (s01 * b2 - b1 * s02)
                   + b0 * (s01 * s12 - s11 * s02)) / determinant
    return intercept, slope_u, slope_v, determinant


def _refined_values(padded_coordinates, padded_modulation, rows, cols, centre, sigma, noise_scale, radius,
                    max_step):
    """The refined coordinate of each weak pixel (NaN where rejected): the plain then the detrended fit,
    as :func:`refine_low_snr` describes."""
    size = 2 * radius + 1
    window = np.lib.stride_tricks.sliding_window_view
    values = window(padded_coordinates, (size, size))[rows, cols].reshape(len(rows), -1)
    modulation = window(padded_modulation, (size, size))[rows, cols].reshape(len(rows), -1)
    finite = np.isfinite(values)
    # the weights B^2, rounded to float32 as the modulation is
    weights = np.where(finite & np.isfinite(modulation), modulation * modulation, 0).astype(np.float64)
    offsets = np.arange(-radius, radius + 1, dtype=np.float64)
    dy, dx = np.repeat(offsets, size), np.tile(offsets, size)
    values64 = values.astype(np.float64)
    refined = np.full(len(rows), np.nan)
    # Decoding errors jump by a period from the locally linear field. First the plain test against the
    # window's median; where it leaves too few neighbours or calls the pixel an outlier (a steep or curved
    # field at a limb changes by more than max_step across the window), the detrended one.
    with np.errstate(invalid="ignore"):
        kept = np.abs(values64 - _finite_medians(values)[:, None]) <= max_step
    intercept, _, _, determinant = _plane_fits(values64, weights, dx, dy, kept)
    count = kept.sum(axis=1)
    plain = (count >= _MIN_NEIGHBOURS) & (determinant > 0.0) & (np.abs(centre - intercept) <= _OUTLIER_SIGMAS * sigma)
    refined[plain] = intercept[plain]
    again = np.flatnonzero(~plain)
    if again.size == 0:
        return refined
    slope_x, slope_y = _neighbour_difference_medians(padded_coordinates, rows[again], cols[again], radius)
    trend = slope_x[:, None] * dx + slope_y[:, None] * dy
    values64 = values64[again]
    detrended = (values64 - trend).astype(np.float32)
    with np.errstate(invalid="ignore"):
        kept = np.abs(values64 - trend - _finite_medians(detrended)[:, None]) <= max_step
    weights = weights[again]
    intercept, slope_u, slope_v, determinant = _plane_fits(values64, weights, dx, dy, kept)
    count = kept.sum(axis=1)
    fitted = (count >= _MIN_NEIGHBOURS) & (determinant > 0.0)
    # The outlier test's sigma, scaled by the fit's reduced chi-square when the plane misfits (a curved
    # coordinate field at a limb), so that model error is not taken for a decoding error.
    with np.errstate(divide="ignore", invalid="ignore"):
        residual = values64 - intercept[:, None] - slope_u[:, None] * dx - slope_v[:, None] * dy
        chi_square = np.where(kept, weights * residual * residual, 0.0).sum(axis=1)
        reduced = chi_square / (noise_scale * noise_scale * (count - 3))
    inflation = np.where(reduced > 1.0, np.sqrt(np.maximum(reduced, 1.0)), 1.0)
    accepted = fitted & (np.abs(centre[again] - intercept) <= _OUTLIER_SIGMAS * sigma[again] * inflation)
    refined[again[accepted]] = intercept[accepted]
    return refined


_CHUNK_PIXELS = 1 << 13  # weak pixels refined per task on the thread pool


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
    coordinates = np.ascontiguousarray(coordinates, dtype=np.float32)
    modulation = np.ascontiguousarray(modulation, dtype=np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        weak = noise_scale / modulation > threshold  # NaN modulation: not refined
    pixels = np.flatnonzero(np.isfinite(coordinates) & weak)
    refined = coordinates.copy()
    if pixels.size == 0:
        return refined
    padded_coordinates, padded_modulation = (
        cv2.copyMakeBorder(image, radius, radius, radius, radius, cv2.BORDER_CONSTANT, value=np.nan)
        for image in (coordinates, modulation))

    def refine_chunk(chunk: slice) -> None:
        here = pixels[chunk]
        rows, cols = np.divmod(here, coordinates.shape[1])
        refined.reshape(-1)[here] = _refined_values(
            padded_coordinates, padded_modulation, rows, cols, np.take(coordinates, here).astype(np.float64),
            noise_scale / np.take(modulation, here).astype(np.float64), float(noise_scale), int(radius),
            float(max_step))

    map_bands(refine_chunk, [slice(first, first + _CHUNK_PIXELS) for first in range(0, pixels.size, _CHUNK_PIXELS)])
    return refined
