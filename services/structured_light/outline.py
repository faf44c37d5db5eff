"""The object's outline in a decoded capture: the camera blur measured across it, and the projector
coordinates beside it, corrected for the bias that the blur causes there or dropped."""

from __future__ import annotations

import math

import cv2
import numba
import numpy as np

from services.structured_light.decode import Rejection

# The camera's total point spread (defocus and pixel area) assumed where the capture shows too few sharp
# outline steps to measure it (a sphere's outline is a limb or a terminator, not a step): a focused
# camera's defocus sigma of 0.7 px and the 1-pixel box of the sensor, variance 1/12 px^2.
ASSUMED_CAMERA_BLUR_PX = float(np.sqrt(0.7**2 + 1 / 12))
# Pixels beside a pixel without signal are always dropped; within the margin of one, so are those whose
# brightness is still below ``_OUTLINE_RAMP`` of the brightest pixel around (the blur ramp). The margin is
# 2.6 blur sigmas to the nearest pixel (2 px for a focused camera, s = 0.76 px), beyond which the blur
# holds 0.5 % of its weight, and the bias is corrected one pixel further; without a correction it is
# 4 sigmas (3 px when focused).
_MARGIN_SIGMAS = 2.6
_UNCORRECTED_MARGIN_SIGMAS = 4.0
_OUTLINE_RAMP = 0.9
# The bias correction: the largest bias corrected rather than dropped (projector pixels), and the largest
# fringe washout s^2 k^2 / 2 for which its first-order form holds.
_MAX_CORRECTED_BIAS = 0.5
_MAX_WASHOUT = 0.5
# The blur estimate: the window over which a step's dark and bright levels are taken (covers +/- 2.6
# sigma of a 1.5 px blur), the part of the step whose slope is measured, the range within which a
# stencil neighbour's share of the step still carries information above the camera noise, the darkest
# share of the bright level that the dark side must reach (a step into darkness, not a texture edge),
# and the fewest measured pixels to trust the median.
_PROFILE_RADIUS_PX = 5
_OUTLINE_REACH_PX = 4  # the middle of a 1.5 px step lies within 3.5 px of its last dark pixel
_STEP_EXTENT = 2.5  # sigmas from the middle of a step to where it is complete
_STEP_TAIL = 0.05
_SAMPLED_SHARE = (0.3, 0.7)
_USABLE_SHARE = (0.01, 0.99)
_MAX_DARK_SHARE = 0.2
_MIN_BLUR_SAMPLES = 100


@numba.njit(cache=True, inline="always")
def _standard_normal_quantile(p):
    """z with Phi(z) = p, by Newton's method on the error function (p within 0.01..0.99: at most 7 steps)."""
    z = 0.0
    for _ in range(20):
        step = (0.5 * math.erfc(-z / math.sqrt(2.0)) - p) * math.sqrt(2.0 * math.pi) * math.exp(0.5 * z * z)
        z -= step
        if abs(step) < 1e-7:
            break
    return z


@numba.njit(cache=True, inline="always")
def _step_share(value, dark, bright):
    """Where a grey level lies between the dark and bright sides of a step, 0..1; NaN outside the usable range."""
    share = (value - dark) / (bright - dark)
    return share if _USABLE_SHARE[0] <= share <= _USABLE_SHARE[1] else np.nan


# Hand-written with numba: a per-pixel edge-width measurement at the few pixels of an outline has no
# library form, and whole-image gradients would cost more than the whole outline step may.
@numba.njit(parallel=True, cache=True)
def _blur_samples_kernel(intensity, rejection, candidate, radius, samples, counts):
    height, width = intensity.shape
    for row in numba.prange(radius, height - radius):
        n = 0
        for col in range(radius + 1, width - radius - 1):
            if candidate[row, col] == 0 or rejection[row, col] != 0:
                continue
            # On a step's middle the intensity changes by more than a tenth of itself per pixel: skip the rest.
            change_x = 0.5 * (intensity[row, col + 1] - intensity[row, col - 1])
            change_y = 0.5 * (intensity[row + 1, col] - intensity[row - 1, col])
            change = math.sqrt(change_x * change_x + change_y * change_y)
            if not change > 0.1 * intensity[row, col]:
                continue
            # The step's dark and bright levels from the profile across it, along the intensity gradient.
            dark, bright, has_dark, has_saturated = np.inf, -np.inf, False, False
            for t in range(-radius, radius + 1):
                r = row + int(round(t * change_y / change))
                c = col + int(round(t * change_x / change))
                dark = min(dark, intensity[r, c])
                bright = max(bright, intensity[r, c])
                has_dark |= rejection[r, c] == Rejection.DARK
                has_saturated |= rejection[r, c] == Rejection.SATURATED
            if not has_dark or has_saturated or not dark <= _MAX_DARK_SHARE * bright:
                continue
            share = (intensity[row, col] - dark) / (bright - dark)
            if not _SAMPLED_SHARE[0] <= share <= _SAMPLED_SHARE[1]:
                continue
            left = _step_share(intensity[row, col - 1], dark, bright)
            right = _step_share(intensity[row, col + 1], dark, bright)
            up = _step_share(intensity[row - 1, col], dark, bright)
            down = _step_share(intensity[row + 1, col], dark, bright)
            if not (np.isfinite(left) and np.isfinite(right) and np.isfinite(up) and np.isfinite(down)):
                continue
            slope_x = 0.5 * (_standard_normal_quantile(right) - _standard_normal_quantile(left))
            slope_y = 0.5 * (_standard_normal_quantile(down) - _standard_normal_quantile(up))
            slope = math.sqrt(slope_x * slope_x + slope_y * slope_y)
            reach = _STEP_EXTENT / slope if slope > 0.0 else np.inf
            if not reach <= radius:
                continue
            # A step complete within its own width, not a gradual fade (a terminator) or a texture edge.
            bright_r = row + int(round(reach * slope_y / slope))
            bright_c = col + int(round(reach * slope_x / slope))
            dark_r = row - int(round(reach * slope_y / slope))
            dark_c = col - int(round(reach * slope_x / slope))
            if (intensity[bright_r, bright_c] - dark) / (bright - dark) < 1.0 - _STEP_TAIL or (
                    intensity[dark_r, dark_c] - dark) / (bright - dark) > _STEP_TAIL:
                continue
            samples[row, n] = 1.0 / slope
            n += 1
        counts[row] = n


@numba.njit(cache=True)
def _median_of_rows(samples, counts):
    """Median of samples[row, :counts[row]] over all rows."""
    pooled = np.empty(counts.sum(), dtype=samples.dtype)
    n = 0
    for row in range(samples.shape[0]):
        pooled[n:n + counts[row]] = samples[row, :counts[row]]
        n += counts[row]
    return np.median(pooled)


def _no_signal_near(rejection: np.ndarray, radius: int) -> np.ndarray:
    """uint8 mask, non-zero within ``radius`` pixels (chessboard distance) of a dark or saturated pixel."""
    no_signal = cv2.inRange(rejection, int(Rejection.DARK), int(Rejection.SATURATED))
    return cv2.dilate(no_signal, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))


def _checked(intensity: np.ndarray, rejection: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    rejection = np.ascontiguousarray(rejection, dtype=np.uint8)
    if intensity.ndim != 2 or intensity.shape != rejection.shape:
        raise ValueError(f"intensity and rejection must be images of the same shape; got {intensity.shape} "
                         f"and {rejection.shape}.")
    return intensity, rejection


def estimate_camera_blur(intensity: np.ndarray, rejection: np.ndarray) -> float | None:
    """The camera's blur, in pixels, from the intensity profile across the object's outline.

    Parameters
    ----------
    intensity : (H, W) float array
        Grey level under the white frame (``DecodedCapture.intensity``).
    rejection : (H, W) uint8 array
        Decoder rejection codes (``DecodedCapture.rejection``); the outline is where ``DARK`` pixels meet
        signal.

    Returns
    -------
    sigma : float or None
        Standard deviation of the camera's total point spread, optics and pixel area together, in camera
        pixels: the median over the outline pixels. None when fewer than 100 outline pixels could be
        measured (no dark outline in view, or only saturated or textured ones).

    Notes
    -----
    The outline of a lit surface against darkness is a step that the camera records convolved with its
    point spread. Near the step, a Gaussian spread of standard deviation s gives the share of the step
    rho = (I - I_dark) / (I_bright - I_dark) = Phi(d / s), d the signed distance to the step, so the probit
    z = Phi^-1(rho) = d / s is linear in the image and |grad z| = 1 / s whatever the step's direction; its
    central differences are exact for a straight step. The pixel's area (a 1-pixel box, variance 1/12)
    widens the step like a Gaussian of the same variance, so s is the total spread, s^2 = sigma_optics^2 +
    1/12 px^2, which is what mixes a pixel's phase with its neighbours'. I_dark and I_bright are the
    extremes within 4 px; a pixel is measured where 0.3 <= rho <= 0.7, its four neighbours lie within
    0.01..0.99 and no saturated pixel is in the window. Shadow edges cast by the projector are blurred by
    the projector's defocus too and lie in the upper tail; the median tolerates them while they are a
    minority of the outline.

    References
    ----------
    .. [1] ISO 12233:2017, "Photography - Electronic still picture imaging - Resolution and spatial
       frequency responses" (edge-based measurement of a camera's spread).
    """
    intensity, rejection = _checked(intensity, rejection)
    height, width = intensity.shape
    samples = np.empty((height, width), dtype=np.float32)  # row buffers, filled only at the outline
    counts = np.zeros(height, dtype=np.int64)
    _blur_samples_kernel(intensity, rejection, _no_signal_near(rejection, _OUTLINE_REACH_PX), _PROFILE_RADIUS_PX,
                         samples, counts)
    if counts.sum() < _MIN_BLUR_SAMPLES:
        return None
    return float(_median_of_rows(samples, counts))


@numba.njit(cache=True, inline="always")
def _log_intensity(intensity, row, col):
    return math.log(max(intensity[row, col], 0.5))


@numba.njit(cache=True, inline="always")
def _distance_to_no_signal(rejection, row, col, limit):
    """Chessboard distance from a pixel to the nearest dark or saturated one, ring by ring; limit + 1 if further."""
    height, width = rejection.shape
    for reach in range(1, limit + 1):
        for r in range(max(0, row - reach), min(height, row + reach + 1)):
            step = 1 if abs(r - row) == reach else 2 * reach
            for c in range(col - reach, col + reach + 1, step):
                if 0 <= c < width and (rejection[r, c] == Rejection.DARK or rejection[r, c] == Rejection.SATURATED):
                    return reach
    return limit + 1


@numba.njit(cache=True, inline="always")
def _brightest_within(intensity, row, col, reach):
    height, width = intensity.shape
    brightest = -np.inf
    for r in range(max(0, row - reach), min(height, row + reach + 1)):
        for c in range(max(0, col - reach), min(width, col + reach + 1)):
            brightest = max(brightest, intensity[r, c])
    return brightest


# Hand-written with numba: the margin and the bias need gradients only at the few pixels near the
# outline, where whole-image gradients and dilations would cost more than the whole outline step may.
@numba.njit(parallel=True, cache=True)
def _outline_kernel(decoded, intensity, rejection, near, margin, reach, variance, wavenumber, out):
    height, width = decoded.shape
    for row in numba.prange(height):
        for col in range(width):
            out[row, col] = decoded[row, col]
            if near[row, col] == 0 or not np.isfinite(decoded[row, col]):
                continue
            distance = _distance_to_no_signal(rejection, row, col, reach)
            if distance <= 1 or (distance <= margin
                                 and intensity[row, col] < _OUTLINE_RAMP * _brightest_within(intensity, row, col, margin)):
                out[row, col] = np.nan
                continue
            if variance == 0.0 or distance > reach:
                continue
            if row == 0 or col == 0 or row == height - 1 or col == width - 1:
                continue
            slope_x = 0.5 * (decoded[row, col + 1] - decoded[row, col - 1])
            slope_y = 0.5 * (decoded[row + 1, col] - decoded[row - 1, col])
            washout = 0.5 * variance * wavenumber * wavenumber * (slope_x * slope_x + slope_y * slope_y)
            if not washout <= _MAX_WASHOUT:  # NaN: a neighbour without a coordinate, left as decoded
                continue
            log_x = 0.5 * (_log_intensity(intensity, row, col + 1) - _log_intensity(intensity, row, col - 1))
            log_y = 0.5 * (_log_intensity(intensity, row + 1, col) - _log_intensity(intensity, row - 1, col))
            bias = variance * (log_x * slope_x + log_y * slope_y)
            out[row, col] = decoded[row, col] - bias if abs(bias) <= _MAX_CORRECTED_BIAS else np.nan


def outline_corrected(coordinates: np.ndarray, intensity: np.ndarray, rejection: np.ndarray,
                      period: float | None, blur_sigma: float | None) -> np.ndarray:
    """Projector coordinates without the outline margin, corrected for the camera blur's bias beside it.

    Parameters
    ----------
    coordinates : (H, W) float array
        Decoded projector coordinates, NaN where rejected.
    intensity, rejection : (H, W) arrays
        ``DecodedCapture.intensity`` and ``DecodedCapture.rejection``.
    period : float or None
        The finest fringe period in projector pixels; None for a Gray-code-only axis, which is not corrected.
    blur_sigma : float or None
        The camera's total point spread s in pixels (:func:`estimate_camera_blur`); None when unknown.

    Returns
    -------
    coordinates : (H, W) float32 array
        NaN at the neighbours of a dark or saturated pixel and, within the margin m = round(2.6 s) of one
        (2 px for s = 0.76 px), where the brightness is below 90 % of the brightest pixel within m (the
        blur ramp); within m + 1, the coordinate less its blur bias b, NaN where |b| > 0.5 projector px.
        Without a period or a blur the bias is not corrected and the wider margin round(4 s) applies
        (3 px for the assumed s).

    Raises
    ------
    ValueError
        If the arrays differ in shape or the blur or period is not positive.

    Notes
    -----
    A camera pixel records sum_x g(x - x0) w(x) exp(i phi(x)) over its point spread g of variance s^2,
    with w the weight of the projected signal (albedo times the cosine of incidence, zero beyond the
    outline). For a locally linear phase that is the phase at the centroid of g w, and for a Gaussian g the
    centroid lies exactly s^2 grad ln (g * w)(x0) from x0, where g * w is the recorded intensity I. The
    coordinate is therefore biased by

        b = s^2 grad ln I . grad x,

    which beside the outline, where I ramps into the dark, is large and measurable. The first-order form
    holds while the fringes are not washed out within the spread, s^2 k^2 / 2 <= 0.5 for the fringe
    wavenumber k = 2 pi |grad x| / P; at a steeper fringe field, and where a neighbour has no coordinate,
    the pixel is left as decoded. Gradients are central differences.

    References
    ----------
    .. [1] Y. Wu, X. Cai, J. Zhu, H. Yue, X. Shao, "Analysis and reduction of the phase error caused by
       the non-impulse system psf in fringe projection profilometry", Optics and Lasers in Engineering
       126, 2020, 105987 (the phase error of a spread point spread function at edges and surface detail).
    .. [2] D. Comaniciu, P. Meer, "Mean shift: a robust approach toward feature space analysis", IEEE
       TPAMI 24(5), 2002 (for a Gaussian kernel, the weighted centroid moves by s^2 grad ln of the
       smoothed weight).
    """
    intensity, rejection = _checked(intensity, rejection)
    coordinates = np.ascontiguousarray(coordinates, dtype=np.float32)
    if coordinates.shape != intensity.shape:
        raise ValueError(f"coordinates must have the shape of the intensity, {intensity.shape}; got "
                         f"{coordinates.shape}.")
    if blur_sigma is not None and not blur_sigma > 0:
        raise ValueError(f"The camera blur must be a positive number of pixels; got {blur_sigma}.")
    if period is not None and not period > 0:
        raise ValueError(f"The fringe period must be a positive number of projector pixels; got {period}.")
    corrected = period is not None and blur_sigma is not None
    spread = ASSUMED_CAMERA_BLUR_PX if blur_sigma is None else float(blur_sigma)
    margin = max(1, round((_MARGIN_SIGMAS if corrected else _UNCORRECTED_MARGIN_SIGMAS) * spread))
    reach = margin + 1 if corrected else margin
    out = np.empty_like(coordinates)
    _outline_kernel(coordinates, intensity, rejection, _no_signal_near(rejection, reach), margin, reach,
                    spread**2 if corrected else 0.0, 2 * np.pi / period if corrected else 0.0, out)
    return out
