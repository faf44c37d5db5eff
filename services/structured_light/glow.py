"""Decoding a capture of a glowing part: the drifting glow removed, thresholds that follow its shot noise.

A hot part adds its own emission to every frame: an offset per pixel that drifts as the part cools,
and shot noise that grows with it. Our hot-part sequences open and close with a black frame
(``generate_sequence(closing_black=True)``); the offset is interpolated in time between the two and
subtracted before any threshold, the camera noise is measured per pixel from the capture itself, and
a pixel whose pattern is too noisy is decoded again over a small window of its neighbours, and one
whose pattern the glow saturates or buries even there gets a rejection code of its own
(``GLOW_SATURATED``, ``GLOW_NOISE``) instead of a coordinate. See docs/hot-parts.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import cv2
import numpy as np

from services.formats.sequence import AXES, Sequence
from services.structured_light.decode import DecodedCapture, Rejection, decode
from services.structured_light.windowed_phase import windowed_frames
from services.structured_light import defaults

# A pixel's phase must be measurable to this standard deviation (radians): with N = 12 steps the
# modulation must then be at least 2.0 sigma, where a Gray plane and its inverse are misread once in 500.
MAX_PHASE_NOISE_RAD = 0.2
_DARK_OF_FULL_SCALE = 0.02  # the cold decoder's darkness limit (decode's default min_intensity)
_NOISE_WINDOW_PX = 9
# Weak pixels are decoded again over a Gaussian window of this sigma on the glowing part (2.4 px FWHM).
WINDOW_SIGMA_PX = 1.0
# A windowed pixel's errors are correlated over its window, so a misread Gray bit there is a blob that the
# speckle filter cannot tell from surface: its modulation must be twice B_min (phase noise 0.1 rad, a Gray
# plane against its inverse at 5.8 sigma, misread once in 10^8).
_WINDOWED_MARGIN = 2.0
_AGREEMENT_SIGMAS = 4.0  # the window's phase within this many of the pixel's own phase noise
_GLOW_OUTLINE_PX = 2  # the camera's point spread (0.76 px) beside a silhouette, as outline.py's margin
_UNLIT_SIGMAS = 3.0  # a glowing pixel whose windowed pattern is below this many sigmas gets no projector light
_LOG_LEVELS = 255  # noise variances are median-filtered as 8-bit codes of log2(variance)
_LOG_RANGE = (-8.0, 40.0)
_HINT_SHARE = 0.05  # the scan result carries a hint when the glow costs more than this share of the part
MIN_MEASURED_SHARE = 0.01
"""A glowing part of which less than this share of the pixels is measured is refused (issue 34's "where the glow
leaves less than 1 % of a part": what is left would be judged as the part). Not tuned: the issue's number."""
MIN_GLOWING_SHARE = 0.001
"""...and only when it glows on at least this share of the camera's pixels (a part, not a glint: 1,024 px of a
1280 x 800 camera), so a few hot pixels in a cold scene never refuse it."""
_JUMP_OF_PERIOD = 0.5  # a coordinate step of half the finest period between neighbours: a depth step (mixed pixels)


def glow_offset(frames: np.ndarray, sequence: Sequence) -> np.ndarray:
    """Per-frame offset of a capture whose sequence opens and closes with a black frame, float32 (F, H, W).

    Notes
    -----
    With D_0, D_1 the black frames at display positions i_0 < i_1, frame f's offset (ambient light,
    projector black level and the part's glow, which cools slowly) is the linear interpolation
    O_f = D_0 + (D_1 - D_0) (f - i_0) / (i_1 - i_0): exact for a drift linear in time over the sequence.
    """
    opening, closing = sequence.black_index, sequence.closing_black_index
    if closing is None:
        raise ValueError("The sequence has no closing black frame, so the glow's drift cannot be interpolated.")
    first = frames[opening].astype(np.float32)
    drift = frames[closing].astype(np.float32) - first
    share = (np.arange(len(frames), dtype=np.float32) - opening) / np.float32(closing - opening)
    return first[None] + share[:, None, None] * drift[None]


def pixel_noise(modulation: np.ndarray, quality: np.ndarray, steps: int) -> np.ndarray:
    """Camera noise per pixel (grey levels), from the residuals of the sinusoid fits in a 9 x 9 window.

    Notes
    -----
    A pixel's residual energy is N B^2 (1 - q) / (2 q) over N - 3 degrees of freedom (see
    ``low_snr.estimate_camera_noise``); its median over the window follows the noise wherever it
    changes slowly, as the glow's shot noise does across a part, and ignores the few pixels whose
    residual is model error (an edge, a mixed pixel). The median is taken of log2 variances coded in
    8 bits (steps of 0.19 octave, 7 % in sigma), which OpenCV's median filter does in milliseconds.
    """
    if steps <= 3:
        raise ValueError("Estimating the noise per pixel needs more than 3 phase steps.")
    b = modulation.astype(np.float64)
    q = quality.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        variance = steps * b * b * (1 - q) / (2 * q * (steps - 3))
    low, high = _LOG_RANGE
    with np.errstate(divide="ignore", invalid="ignore"):
        code = (np.log2(variance) - low) / (high - low) * _LOG_LEVELS
    code = np.where(np.isfinite(code), code, _LOG_LEVELS)  # no fit (a flat pixel): assume the worst
    code = np.clip(np.rint(code), 0, _LOG_LEVELS).astype(np.uint8)
    smoothed = cv2.medianBlur(cv2.medianBlur(code, 5), 5)  # two 5x5 passes: about a 9x9 median
    return np.sqrt(2.0 ** (low + smoothed.astype(np.float32) * np.float32((high - low) / _LOG_LEVELS)))


@dataclass(frozen=True)
class GlowReport:
    """What the glow did to one scan.

    Attributes
    ----------
    glowing_fraction : float
        Share of the camera's pixels where the glow is at least 2 % of full scale and at least the
        reflected pattern: the hot part as the camera sees it.
    saturated_fraction, lost_fraction : float
        Shares of those glowing pixels rejected because the glow saturated their pattern
        (``GLOW_SATURATED``) or buried it in its shot noise (``GLOW_NOISE`` where a windowed average
        still detects projector light).
    measured_fraction : float
        Share of those glowing pixels that were measured, counted 2 px inside the glowing region's outline
        (its silhouette's pixels mix the part with the background): by ``decode_glowing``, those given a
        projector coordinate; by ``reconstruct_scan``, those that kept a point (:meth:`measured`).
    inner_glowing : (H, W) bool array or None
        Those glowing pixels 2 px inside the outline (not serialised).
    glow_level : float
        99th percentile of the glow, as a fraction of full scale.
    drift : float
        Median relative change of the glow from the opening to the closing black frame on the glowing
        pixels (negative: the part cooled).
    hint : str or None
        What to change when the glow costs more than 5 % of the part.
    """

    glowing_fraction: float
    saturated_fraction: float
    lost_fraction: float
    glow_level: float
    drift: float
    hint: str | None
    measured_fraction: float = 1.0
    inner_glowing: np.ndarray | None = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        values = {item.name: getattr(self, item.name) for item in fields(self) if item.name != "inner_glowing"}
        return {key: (round(value, 5) if isinstance(value, float) else value) for key, value in values.items()}

    def measured(self, has_point: np.ndarray) -> GlowReport:
        """The report with ``measured_fraction`` of the glowing pixels that have a point (``has_point``, (H, W))."""
        if self.inner_glowing is None or not self.inner_glowing.any():
            return self
        return replace(self, measured_fraction=float(np.mean(has_point[self.inner_glowing])))

    def refusal(self) -> str | None:
        """Why a capture must not be measured at all (less than :data:`MIN_MEASURED_SHARE` of a glowing part
        measured), or None."""
        if self.glowing_fraction < MIN_GLOWING_SHARE or self.measured_fraction >= MIN_MEASURED_SHARE:
            return None
        hint = self.hint or _hint(self.saturated_fraction, 1.0 - self.saturated_fraction)
        return (f"the part's glow leaves {self.measured_fraction:.2%} of it measured (less than "
                f"{MIN_MEASURED_SHARE:.0%}: {self.saturated_fraction:.0%} of its glowing pixels saturated, the rest "
                f"buried in the glow's shot noise or unlit); no cloud is made, since the points left would be "
                f"judged as the part: {hint}")


def _hint(saturated: float, lost: float) -> str | None:
    if saturated + lost <= _HINT_SHARE:
        return None
    if saturated >= lost:
        return ("the part's glow saturates the camera: use a shorter exposure (automatic exposure or HDR), "
                "or a blue projector and a band-pass filter")
    return ("the part's glow buries the pattern in its shot noise: use a blue projector and a band-pass "
            "filter on the camera")


def _windowed_recovery(decoded: DecodedCapture, own: dict[str, np.ndarray], clean: np.ndarray, sequence: Sequence,
                       glowing: np.ndarray, noise: np.ndarray, least_modulation: np.ndarray, steps: int, *,
                       min_quality: float, consistency: float, max_jump: float,
                       sigma_px: float) -> tuple[DecodedCapture, np.ndarray]:
    """``GLOW_NOISE`` pixels decoded again from windowed frames (``windowed_phase.windowed_frames``) over
    the glowing part, kept where the window's phase meets the same noise standard and agrees with the
    pixel's own phase; and the map of the glowing pixels that no projector light reaches (the window's
    mean phase-frame level within 3 of its sigmas of the glow)."""
    weak = decoded.rejection == Rejection.GLOW_NOISE
    # The glowing surface, dark and noisy pixels included (they add noise, no bias), less the pixels
    # whose samples are clipped or that straddle a depth step.
    support = glowing & ~np.isin(decoded.rejection, (Rejection.GLOW_SATURATED, Rejection.SATURATED, Rejection.EDGE))
    windowed, noise_gain, _ = windowed_frames(clean, sequence, support, sigma_px=sigma_px)
    again = decode(windowed, sequence, saturation_level=np.inf, min_intensity=-np.inf, min_modulation=0.0,
                   min_quality=min_quality, consistency=consistency, edge_margin=0, max_jump=max_jump)
    with np.errstate(divide="ignore", invalid="ignore"):
        effective = again.modulation / noise_gain  # the windowed modulation against the pixel's own noise
    agrees = np.ones(weak.shape, dtype=bool)
    for axis in AXES:
        if not sequence.phase_groups(axis):
            continue
        period = sequence.phase_groups(axis)[-1].period
        with np.errstate(divide="ignore", invalid="ignore"):
            own_spread = period / (2 * np.pi) * noise * np.float32(np.sqrt(2.0 / steps)) / again.modulation
        step = np.remainder(getattr(again, f"projector_{axis}") - own[axis] + period / 2, period) - period / 2
        agrees &= ~np.isfinite(own[axis]) | (np.abs(step) <= _AGREEMENT_SIGMAS * own_spread)
    recovered = (weak & (again.rejection == Rejection.VALID) & (effective >= _WINDOWED_MARGIN * least_modulation)
                 & agrees)
    phase_frames = [i for group in sequence.phase_groups() for i in group.frames]
    lit_level = np.mean(windowed[phase_frames], axis=0)
    with np.errstate(invalid="ignore"):
        unlit = glowing & (lit_level < _UNLIT_SIGMAS * noise * noise_gain / np.float32(np.sqrt(len(phase_frames))))
    rejection = decoded.rejection.copy()
    rejection[recovered] = Rejection.VALID
    fields = {}
    for name in ("projector_x", "projector_y", "modulation", "quality"):
        values = getattr(decoded, name).copy()
        values[recovered] = (effective if name == "modulation" else getattr(again, name))[recovered]
        fields[name] = values
    return replace(decoded, rejection=rejection, **fields), unlit


def _glow_outline(decoded: DecodedCapture, glowing: np.ndarray) -> DecodedCapture:
    """Valid pixels that do not glow within 2 px of a glowing pixel without a coordinate become ``EDGE``:
    the part's silhouette against a cooler surface, where a pixel mixes the glowing part, whose pattern
    is lost, with the surface beyond it, whose pattern it then reads at a ray that sees the part."""
    lost = (glowing & (decoded.rejection != Rejection.VALID)).astype(np.uint8)
    size = 2 * _GLOW_OUTLINE_PX + 1
    near = cv2.dilate(lost, np.ones((size, size), np.uint8)).astype(bool)
    edge = near & ~glowing & (decoded.rejection == Rejection.VALID)
    if not edge.any():
        return decoded
    rejection = decoded.rejection.copy()
    rejection[edge] = Rejection.EDGE
    x, y = decoded.projector_x.copy(), decoded.projector_y.copy()
    x[edge] = np.nan
    y[edge] = np.nan
    return replace(decoded, projector_x=x, projector_y=y, rejection=rejection)


def _unlit_as_shadow(decoded: DecodedCapture, unlit: np.ndarray) -> DecodedCapture:
    """``GLOW_NOISE`` pixels that no projector light reaches (``unlit``) become ``LOW_MODULATION``.

    Parameters
    ----------
    decoded : DecodedCapture
        After the windowed recovery.
    unlit : (H, W) bool array
        Glowing pixels whose windowed pattern is below ``_UNLIT_SIGMAS`` of its noise.

    Returns
    -------
    DecodedCapture
        With those pixels' rejection ``LOW_MODULATION`` (their coordinates are NaN already).

    Notes
    -----
    Such a pixel is in a projector shadow (cast by the part on itself, or by a fixture) or faces away from
    the projector: it has no pattern to lose, as a shadowed pixel of a cool surface has none, which the
    decoder calls ``LOW_MODULATION``. The code matters to the outline step: pixels without a pattern
    (``outline._no_pattern``: dark, saturated, low modulation, saturated by the glow) seed its margin, and a
    pixel a blur sigma inside the shadow, which holds only its lit neighbour's blurred fringes (Phi(-1) = 16 %
    of them) and so the neighbour's code, is dropped there when its modulation is below 90 % of the strongest
    within the margin (docs/structured-light.md, "Points at projector shadows and depth steps"). As
    ``GLOW_NOISE`` the shadow seeded nothing and that pixel was kept, 1 to 5 mm off along its line of
    sight. ``GLOW_NOISE`` pixels with projector light (a pattern buried in the glow's shot noise) are not
    seeds: a noisy part's scattered weak pixels would drop their neighbours, whose codes are their own.
    The unlit test is the windowed phase-frame level against 3 of its noise sigmas [1]_.

    References
    ----------
    .. [1] C. Zuo et al., "Phase shifting algorithms for fringe projection profilometry: a review",
       Optics and Lasers in Engineering 109, 2018, section 5 (the modulation's noise, sigma sqrt(2 / N)).
    """
    if unlit.shape != decoded.rejection.shape:
        raise ValueError(f"The unlit map must have the capture's shape {decoded.rejection.shape}; got {unlit.shape}.")
    shadow = unlit & (decoded.rejection == Rejection.GLOW_NOISE)
    if not shadow.any():
        return decoded
    rejection = decoded.rejection.copy()
    rejection[shadow] = Rejection.LOW_MODULATION
    return replace(decoded, rejection=rejection)


def decode_glowing(
    frames: np.ndarray,
    sequence: Sequence,
    *,
    saturation_level: float | None = None,
    min_quality: float = 0.5,
    consistency: float = defaults.CONSISTENCY,
    max_phase_noise: float = MAX_PHASE_NOISE_RAD,
    window_sigma_px: float = WINDOW_SIGMA_PX,
) -> tuple[DecodedCapture, np.ndarray, GlowReport]:
    """Decode a capture of a glowing part whose sequence opens and closes with a black frame.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        One camera frame per manifest frame, in display order.
    sequence : Sequence
        With a phase-coded axis and a closing black frame.
    saturation_level : float, optional
        Grey level at which the sensor saturates (4095 for 12-bit frames); default the dtype maximum.
    min_quality, consistency : float
        As in :func:`decode`.
    max_phase_noise : float
        Largest phase standard deviation (radians) that the noise may leave a valid pixel.
    window_sigma_px : float
        Sigma (camera pixels) of the Gaussian window over which ``GLOW_NOISE`` pixels are decoded again;
        0 leaves them rejected.

    Returns
    -------
    decoded : DecodedCapture
        ``intensity`` is the pattern's white level above the offset; ``rejection`` adds
        ``GLOW_SATURATED`` and ``GLOW_NOISE``; glowing pixels that no projector light reaches are
        ``LOW_MODULATION``.
    noise : (H, W) float32 array
        The camera noise per pixel, grey levels (``pixel_noise``).
    report : GlowReport

    Notes
    -----
    Frames minus their interpolated offset (``glow_offset``) are decoded without intensity or
    saturation limits; then per pixel, in this order: a raw frame at ``saturation_level`` is
    ``GLOW_SATURATED`` where the pixel glows (glow >= 2 % of full scale and >= the pattern) and
    ``SATURATED`` elsewhere; with sigma the pixel's noise and B_min = sigma sqrt(2 / N) /
    max_phase_noise the least modulation whose phase is that precise (sigma_phi = sigma sqrt(2 / N) / B
    [1]_), a pattern below 2 % of full scale is ``DARK`` where 2 B_min is below that (a pattern could
    have been seen); a modulation below B_min is ``GLOW_NOISE`` where the pixel glows and
    ``LOW_MODULATION`` elsewhere.

    A ``GLOW_NOISE`` pixel is then decoded again from frames averaged over a Gaussian window on the
    glowing part, fringes demodulated by their local frequency (``windowed_phase.windowed_frames``,
    windowed Fourier filtering [2]_), and kept where that window's modulation is at least 2 B_min g, g
    the window's noise gain (about 0.29 for sigma = 1 px: a phase noise of 0.1 rad), its decode is valid,
    and its phase lies within 4 of the pixel's own phase-noise sigmas of the pixel's own phase (a window
    across a depth step disagrees with its centre). Its ``modulation`` is then the window's divided by
    g, the modulation a single pixel of that precision would have. Last, valid pixels that do not glow
    within 2 px of a glowing pixel without a coordinate are ``EDGE`` (the part's silhouette against a
    cooler surface, which no coordinate jump reveals when the part's side is lost).
    ``GlowReport.lost_fraction`` counts the ``GLOW_NOISE`` pixels whose windowed pattern is at least 3
    sigma above the glow: a part's surfaces that the projector does not light are not lost to the glow.
    Those unlit pixels (with ``window_sigma_px`` > 0) are ``LOW_MODULATION`` in the result, a projector shadow
    as on a cool surface, so that the outline step's pattern margin drops the leaked codes beside them
    (``_unlit_as_shadow``).

    References
    ----------
    .. [1] C. Zuo et al., "Phase shifting algorithms for fringe projection profilometry: a review",
       Optics and Lasers in Engineering 109, 2018, section 5.
    .. [2] Q. Kemao, "Two-dimensional windowed Fourier transform for fringe pattern analysis: principles,
       applications and implementations", Optics and Lasers in Engineering 45(2), 304-317, 2007.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"Frames must be a (F, H, W) uint8 or uint16 stack; got {frames.shape} {frames.dtype}.")
    if len(frames) != len(sequence.frames):
        raise ValueError(f"The sequence has {len(sequence.frames)} frames but {len(frames)} were given.")
    groups = sequence.phase_groups()
    if not groups:
        raise ValueError("Decoding a glowing part needs phase-shifted frames to measure the noise from.")
    full_scale = float(np.iinfo(frames.dtype).max if saturation_level is None else saturation_level)
    offset = glow_offset(frames, sequence)
    clean = frames.astype(np.float32) - offset
    max_jump = _JUMP_OF_PERIOD * min(group.period for group in groups)
    decoded = decode(clean, sequence, saturation_level=np.inf, min_intensity=-np.inf, min_modulation=0.0,
                     min_quality=min_quality, consistency=consistency, edge_margin=0, max_jump=max_jump)
    steps = min(len(group.frames) for group in groups)
    noise = pixel_noise(decoded.modulation, decoded.quality, steps)

    glow = 0.5 * (offset[sequence.black_index] + offset[sequence.closing_black_index])
    coded = [i for i, frame in enumerate(sequence.frames) if frame.kind in ("gray", "phase")]
    saturated = np.any(frames[coded] >= full_scale, axis=0)
    glowing = (glow >= _DARK_OF_FULL_SCALE * full_scale) & (saturated | (glow >= decoded.intensity))
    least_modulation = noise * np.float32(np.sqrt(2.0 / steps) / max_phase_noise)
    dark_limit = _DARK_OF_FULL_SCALE * full_scale
    rejection = decoded.rejection.copy()
    weak = decoded.modulation < least_modulation
    codes = [
        (saturated & glowing, Rejection.GLOW_SATURATED),
        (saturated & ~glowing, Rejection.SATURATED),
        ((decoded.intensity < dark_limit) & (2 * least_modulation < dark_limit) & ~glowing, Rejection.DARK),
        (weak & glowing, Rejection.GLOW_NOISE),
        (weak & ~glowing, Rejection.LOW_MODULATION),
    ]
    decided = np.zeros(rejection.shape, dtype=bool)
    for where, code in codes:
        where = where & ~decided
        rejection[where] = code
        decided |= where
    rejected = rejection != Rejection.VALID
    own = {"x": decoded.projector_x, "y": decoded.projector_y}  # before rejection, for the windowed check
    x, y = decoded.projector_x.copy(), decoded.projector_y.copy()
    x[rejected] = np.nan
    y[rejected] = np.nan
    decoded = replace(decoded, projector_x=x, projector_y=y, rejection=rejection)
    unlit = np.zeros(rejection.shape, dtype=bool)
    if window_sigma_px > 0 and np.any(rejection == Rejection.GLOW_NOISE):
        decoded, unlit = _windowed_recovery(decoded, own, clean, sequence, glowing, noise, least_modulation, steps,
                                            min_quality=min_quality, consistency=consistency, max_jump=max_jump,
                                            sigma_px=window_sigma_px)
    decoded = _glow_outline(decoded, glowing)
    decoded = _unlit_as_shadow(decoded, unlit)
    rejection = decoded.rejection

    saturated_share, lost_share, drift, measured_share, inner = 0.0, 0.0, 0.0, 1.0, None
    if glowing.any():
        codes_glowing = rejection[glowing]
        # measured on the part: its silhouette's ring, where the camera's blur mixes it with the background, is left out
        size = 2 * _GLOW_OUTLINE_PX + 1
        inner = cv2.erode(glowing.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
        inner = inner if inner.any() else glowing
        measured_share = float(np.mean(rejection[inner] == Rejection.VALID))
        saturated_share = float(np.mean(codes_glowing == Rejection.GLOW_SATURATED))
        lost_share = float(np.mean((codes_glowing == Rejection.GLOW_NOISE) & ~unlit[glowing]))
        opening = offset[sequence.black_index][glowing]
        closing = offset[sequence.closing_black_index][glowing]
        drift = float(np.median((closing - opening) / np.maximum(opening, 1.0)))
    report = GlowReport(glowing_fraction=float(glowing.mean()), saturated_fraction=saturated_share,
                        lost_fraction=lost_share, glow_level=float(np.percentile(glow, 99)) / full_scale,
                        drift=drift, hint=_hint(saturated_share, lost_share), measured_fraction=measured_share,
                        inner_glowing=inner)
    return decoded, noise, report
