"""The object's outline in a decoded capture: the camera blur measured across it, and the projector
coordinates beside it, corrected for the bias that the blur causes there or dropped."""

from __future__ import annotations

import cv2
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
# Within the margin of a pixel without a projected pattern (the pattern's outline, which ambient light or a
# hot part's glow hides from the brightness), pixels whose modulation is below this share of the strongest
# within the margin are dropped: a pixel a blur sigma inside a projector shadow keeps Phi(-1) = 16 % of its
# lit neighbour's pattern, and its code. Chosen on the shadow tuning scene (experiments/shadow_scene.py,
# docs/structured-light.md): it removes the leaks there while the paper sphere's terminator, where the
# pattern fades by the cosine of incidence, keeps its coverage.
SHADOW_CONTRAST = 0.9
_STEP_COMPLETE = 0.7
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


# Acklam's rational approximation of the standard normal quantile (relative error below 1.15e-9):
# P. J. Acklam, "An algorithm for computing the inverse normal cumulative distribution function" (2003),
# https://web.archive.org/web/20151030215612/http://home.online.no/~pjacklam/notes/invnorm/
_ACKLAM_A = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02, 1.383577518672690e+02,
             -3.066479806614716e+01, 2.506628277459239e+00)
_ACKLAM_B = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02, 6.680131188771972e+01,
             -1.328068155288572e+01, 1.0)
_ACKLAM_C = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00, -2.549732539343734e+00,
             4.374664141464968e+00, 2.938163982698783e+00)
_ACKLAM_D = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00, 1.0)
_ACKLAM_TAIL = 0.02425


def _standard_normal_quantile(p: np.ndarray) -> np.ndarray:
    """z with Phi(z) = p for p in (0, 1), elementwise, to a relative 1.15e-9 (Acklam's approximation)."""
    p = np.asarray(p, np.float64)
    q = p - 0.5
    r = q * q
    z = q * np.polyval(_ACKLAM_A, r) / np.polyval(_ACKLAM_B, r)
    tail = np.minimum(p, 1.0 - p) < _ACKLAM_TAIL
    if tail.any():
        pt = p[tail]
        t = np.sqrt(-2.0 * np.log(np.minimum(pt, 1.0 - pt)))
        zt = np.polyval(_ACKLAM_C, t) / np.polyval(_ACKLAM_D, t)
        z[tail] = np.where(pt < 0.5, zt, -zt)
    return z


def _step_share(value: np.ndarray, dark: np.ndarray, bright: np.ndarray) -> np.ndarray:
    """Where grey levels lie between the dark and bright sides of a step, 0..1; NaN outside the usable range."""
    share = (value - dark) / (bright - dark)
    return np.where((share >= _USABLE_SHARE[0]) & (share <= _USABLE_SHARE[1]), share, np.nan)


def _rounded(values: np.ndarray) -> np.ndarray:
    """Python's round to an integer (half to even), elementwise."""
    return np.rint(values).astype(np.intp)


# In numpy on the few candidate pixels of the outline (np.nonzero of the candidate mask, then arithmetic
# on their index arrays): whole-image gradients would cost more than the whole outline step may.
def _blur_samples(intensity: np.ndarray, rejection: np.ndarray, candidate: np.ndarray, radius: int) -> np.ndarray:
    """1 / |grad Phi^-1(share)| at the outline pixels that show a clean step (see
    :func:`estimate_camera_blur`), float32."""
    height, width = intensity.shape
    inner = np.zeros(candidate.shape, bool)
    inner[radius:height - radius, radius + 1:width - radius - 1] = True
    row, col = np.nonzero(inner & (candidate != 0) & (rejection == 0))

    def at(r, c):
        return intensity[r, c].astype(np.float64)

    # On a step's middle the intensity changes by more than a tenth of itself per pixel: skip the rest.
    change_x = 0.5 * (intensity[row, col + 1] - intensity[row, col - 1]).astype(np.float64)
    change_y = 0.5 * (intensity[row + 1, col] - intensity[row - 1, col]).astype(np.float64)
    change = np.sqrt(change_x * change_x + change_y * change_y)
    keep = change > 0.1 * at(row, col)
    row, col, change_x, change_y, change = row[keep], col[keep], change_x[keep], change_y[keep], change[keep]
    # The step's dark and bright levels from the profile across it, along the intensity gradient.
    t = np.arange(-radius, radius + 1)[None, :]
    profile_r = row[:, None] + _rounded(t * change_y[:, None] / change[:, None])
    profile_c = col[:, None] + _rounded(t * change_x[:, None] / change[:, None])
    values = intensity[profile_r, profile_c]
    codes = rejection[profile_r, profile_c]
    dark, bright = values.min(axis=1).astype(np.float64), values.max(axis=1).astype(np.float64)
    keep = ((codes == Rejection.DARK).any(axis=1) & ~(codes == Rejection.SATURATED).any(axis=1)
            & (dark <= _MAX_DARK_SHARE * bright))
    share = (at(row, col) - dark) / (bright - dark)
    keep &= (share >= _SAMPLED_SHARE[0]) & (share <= _SAMPLED_SHARE[1])
    row, col, dark, bright = row[keep], col[keep], dark[keep], bright[keep]
    shares = [_step_share(at(r, c), dark, bright) for r, c in
              ((row, col - 1), (row, col + 1), (row - 1, col), (row + 1, col))]
    keep = np.all(np.isfinite(shares), axis=0)
    row, col, dark, bright = row[keep], col[keep], dark[keep], bright[keep]
    left, right, up, down = (_standard_normal_quantile(share[keep]) for share in shares)
    slope_x = 0.5 * (right - left)
    slope_y = 0.5 * (down - up)
    slope = np.sqrt(slope_x * slope_x + slope_y * slope_y)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(slope > 0.0, _STEP_EXTENT / slope, np.inf)
    keep = reach <= radius
    row, col, dark, bright = row[keep], col[keep], dark[keep], bright[keep]
    slope_x, slope_y, slope, reach = slope_x[keep], slope_y[keep], slope[keep], reach[keep]
    # A step complete within its own width, not a gradual fade (a terminator) or a texture edge.
    step_r, step_c = _rounded(reach * slope_y / slope), _rounded(reach * slope_x / slope)
    keep = ~(((at(row + step_r, col + step_c) - dark) / (bright - dark) < 1.0 - _STEP_TAIL)
             | ((at(row - step_r, col - step_c) - dark) / (bright - dark) > _STEP_TAIL))
    return (1.0 / slope[keep]).astype(np.float32)


def _no_signal(rejection: np.ndarray) -> np.ndarray:
    """uint8 mask, non-zero at the dark or saturated pixels."""
    return cv2.inRange(rejection, int(Rejection.DARK), int(Rejection.SATURATED))


def _no_pattern(rejection: np.ndarray) -> np.ndarray:
    """uint8 mask, non-zero at the pixels without a projected pattern: dark, saturated, low modulation (a
    projector shadow under ambient light or a hot part's glow) or saturated by the glow."""
    return (cv2.inRange(rejection, int(Rejection.DARK), int(Rejection.LOW_MODULATION))
            | (rejection == Rejection.GLOW_SATURATED).view(np.uint8))


def _near(mask: np.ndarray, radius: int) -> np.ndarray:
    """uint8 mask, non-zero within ``radius`` pixels (chessboard distance) of a non-zero pixel of ``mask``."""
    return cv2.dilate(mask, np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))


def _no_signal_near(rejection: np.ndarray, radius: int) -> np.ndarray:
    """uint8 mask, non-zero within ``radius`` pixels (chessboard distance) of a dark or saturated pixel."""
    return _near(_no_signal(rejection), radius)


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
    samples = _blur_samples(intensity, rejection, _no_signal_near(rejection, _OUTLINE_REACH_PX), _PROFILE_RADIUS_PX)
    if samples.size < _MIN_BLUR_SAMPLES:
        return None
    return float(np.median(samples))


def _log_intensity(intensity: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    return np.log(np.maximum(intensity[row, col].astype(np.float64), 0.5))


def _distance_to_no_signal(no_signal: np.ndarray, row: np.ndarray, col: np.ndarray, limit: int) -> np.ndarray:
    """Chessboard distance from each pixel to the nearest other pixel of the uint8 mask ``no_signal``; limit + 1
    if further."""
    distance = np.full(row.shape, limit + 1, np.int64)
    for reach in range(limit, 0, -1):  # nearest last
        ring = np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)
        ring[reach, reach] = 0  # the pixel itself does not count
        distance[cv2.dilate(no_signal, ring)[row, col] != 0] = reach
    return distance


def _brightest_within(intensity: np.ndarray, row: np.ndarray, col: np.ndarray, reach: int) -> np.ndarray:
    """The largest grey level within ``reach`` pixels (chessboard) of each pixel, inside the image."""
    height, width = intensity.shape
    brightest = np.full(row.shape, -np.inf, np.float32)
    for dr in range(-reach, reach + 1):
        r = np.clip(row + dr, 0, height - 1)  # a clipped index repeats a pixel of the window
        for dc in range(-reach, reach + 1):
            np.maximum(brightest, intensity[r, np.clip(col + dc, 0, width - 1)], out=brightest)
    return brightest


# In numpy on the few pixels near the outline (np.nonzero of the mask, then arithmetic on their index
# arrays), where whole-image gradients and dilations would cost more than the whole outline step may.
def _outline_pixels(decoded, intensity, no_signal, margin, reach, variance, wavenumber,
                    modulation=None, no_pattern=None, drop_washed_out=False) -> np.ndarray:
    height, width = decoded.shape
    out = decoded.copy()
    row, col = np.nonzero((_near(no_signal, reach) != 0) & np.isfinite(decoded))
    distance = _distance_to_no_signal(no_signal, row, col, reach)
    ramp = (distance > 1) & (distance <= margin)
    dropped = distance <= 1
    dropped[ramp] = intensity[row[ramp], col[ramp]] < _OUTLINE_RAMP * _brightest_within(
        intensity, row[ramp], col[ramp], margin).astype(np.float64)
    out[row[dropped], col[dropped]] = np.nan
    if modulation is not None:
        # The pattern's own outline (a projector shadow under room light or glow): within the margin of a
        # pixel without a pattern, a pixel whose pattern is below a share of the strongest around it is
        # mostly its lit neighbour's blurred pattern, carrying the neighbour's code.
        # A step that completes within the margin (the strongest pattern within it is most of that within
        # three times it), not the gradual fade of a terminator, where the pattern is the pixel's own.
        leak_row, leak_col = np.nonzero((_near(no_pattern, margin) != 0) & np.isfinite(out))
        strongest = _brightest_within(modulation, leak_row, leak_col, margin).astype(np.float64)
        leaked = (modulation[leak_row, leak_col] < SHADOW_CONTRAST * strongest) & (
            strongest >= _STEP_COMPLETE * _brightest_within(modulation, leak_row, leak_col, 3 * margin))
        out[leak_row[leaked], leak_col[leaked]] = np.nan
        dropped |= np.isnan(out[row, col])
    if variance == 0.0:
        return out
    keep = ~dropped & (distance <= reach) & (row > 0) & (col > 0) & (row < height - 1) & (col < width - 1)
    row, col = row[keep], col[keep]
    slope_x = 0.5 * (decoded[row, col + 1] - decoded[row, col - 1]).astype(np.float64)
    slope_y = 0.5 * (decoded[row + 1, col] - decoded[row - 1, col]).astype(np.float64)
    washout = 0.5 * variance * wavenumber * wavenumber * (slope_x * slope_x + slope_y * slope_y)
    keep = washout <= _MAX_WASHOUT  # NaN: a neighbour without a coordinate, left as decoded
    if drop_washed_out:  # interpolated between Gray boundaries that the blur no longer locates
        washed = ~keep & np.isfinite(washout)
        out[row[washed], col[washed]] = np.nan
    row, col, slope_x, slope_y = row[keep], col[keep], slope_x[keep], slope_y[keep]
    log_x = 0.5 * (_log_intensity(intensity, row, col + 1) - _log_intensity(intensity, row, col - 1))
    log_y = 0.5 * (_log_intensity(intensity, row + 1, col) - _log_intensity(intensity, row - 1, col))
    bias = variance * (log_x * slope_x + log_y * slope_y)
    out[row, col] = np.where(np.abs(bias) <= _MAX_CORRECTED_BIAS, decoded[row, col] - bias, np.nan)
    return out


def outline_corrected(coordinates: np.ndarray, intensity: np.ndarray, rejection: np.ndarray,
                      period: float | None, blur_sigma: float | None,
                      modulation: np.ndarray | None = None, boundaries: bool = False) -> np.ndarray:
    """Projector coordinates without the outline margin, corrected for the camera blur's bias beside it.

    Parameters
    ----------
    coordinates : (H, W) float array
        Decoded projector coordinates, NaN where rejected.
    intensity, rejection : (H, W) arrays
        ``DecodedCapture.intensity`` and ``DecodedCapture.rejection``.
    period : float or None
        The finest fringe period in projector pixels (for coordinates interpolated between Gray stripe
        boundaries, that of the finest Gray plane, four stripes); None for Gray stripe centres, which are
        not corrected.
    blur_sigma : float or None
        The camera's total point spread s in pixels (:func:`estimate_camera_blur`); None when unknown.
    modulation : (H, W) array, optional
        ``DecodedCapture.modulation``. When given, the outline is where the projected pattern ends: pixels
        without a pattern (dark, saturated, low modulation, saturated by a hot part's glow) seed the margin,
        and the ramp and the bias follow the modulation, the weight w of the pattern (Notes), rather than the
        brightness, which holds ambient light and glow. A projector shadow under room light or beside a
        glowing part is then an outline too: the pixels a pixel or two inside it carry only the blurred
        pattern of their lit neighbour, and its code. Without it, only dark and saturated pixels count and
        the brightness is the weight.
    boundaries : bool
        The coordinates were interpolated between Gray-code stripe boundaries (``gray_subpixel``): where the
        finest plane washes out within the spread its boundaries are not located, so such pixels within the
        corrected band are dropped rather than left as decoded.

    Returns
    -------
    coordinates : (H, W) float32 array
        NaN at the neighbours of a pixel without signal and, within the margin m = round(2.6 s) of one
        (2 px for s = 0.76 px), where the weight is below 90 % of the largest within m (the blur ramp);
        within m + 1, the coordinate less its blur bias b, NaN where |b| > 0.5 projector px. Without a
        period or a blur the bias is not corrected and the wider margin round(4 s) applies (3 px for the
        assumed s).

    Raises
    ------
    ValueError
        If the arrays differ in shape or the blur or period is not positive.

    Notes
    -----
    A camera pixel records sum_x g(x - x0) w(x) exp(i phi(x)) over its point spread g of variance s^2,
    with w the weight of the projected signal (albedo times the cosine of incidence, zero beyond the
    outline). For a locally linear phase that is the phase at the centroid of g w, and for a Gaussian g the
    centroid lies exactly s^2 grad ln (g * w)(x0) from x0, where g * w is the recorded modulation (or, without
    ambient light, the intensity) I. The coordinate is therefore biased by

        b = s^2 grad ln I . grad x,

    which beside the outline, where I ramps into the dark, is large and measurable. The first-order form
    holds while the fringes are not washed out within the spread, s^2 k^2 / 2 <= 0.5 for the fringe
    wavenumber k = 2 pi |grad x| / P; at a steeper fringe field, and where a neighbour has no coordinate,
    the pixel is left as decoded. Gradients are central differences. A Gray-code stripe boundary located
    where a blurred plane crosses its threshold is shifted alike: for w locally exp(a . x) the zero crossing
    of g * (w sign) lies s^2 a from the true edge, so coordinates interpolated between such boundaries carry
    the same b, while the finest plane (period four stripes) is not washed out.

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
    no_pattern = None
    if modulation is not None:
        modulation = np.ascontiguousarray(modulation, dtype=np.float32)
        if modulation.shape != intensity.shape:
            raise ValueError(f"modulation must have the shape of the intensity, {intensity.shape}; got "
                             f"{modulation.shape}.")
        no_pattern = _no_pattern(rejection)
    return _outline_pixels(coordinates, intensity, _no_signal(rejection), margin, reach,
                           spread**2 if corrected else 0.0, 2 * np.pi / period if corrected else 0.0,
                           modulation, no_pattern, boundaries)
