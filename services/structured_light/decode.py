"""Decoding a structured-light capture: sub-pixel projector coordinates per camera pixel.

Any sequence a manifest can describe is decoded in one pass over the pixels:
Gray-code planes (against their inverse, the white/black mid level or the
phase offset), N-step phase shifting at one or several periods, and their
combination, with the phase unwrapped against the Gray-code stripe centre.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from services.formats.sequence import AXES, Sequence


class Rejection(enum.IntEnum):
    """Why a camera pixel has no projector coordinate (the ``rejection`` map); checked in this order."""

    VALID = 0
    DARK = 1  #: intensity below ``min_intensity``: outside the projector's light or too dark
    SATURATED = 2  #: a phase frame (any frame if none) reaches ``saturation_level``: clipping biases the phase
    LOW_MODULATION = 3  #: the projected signal is below ``min_modulation``: projector shadow, glare, dark surface
    POOR_FIT = 4  #: ``quality`` below ``min_quality``: the samples are not one sinusoid (mixed or moving surface)
    INCONSISTENT = 5  #: Gray code and phase (or two phase periods) disagree, or the code is out of range
    EDGE = 6  #: next to a rejected pixel or across a coordinate jump: a camera pixel mixing two surfaces


@dataclass(frozen=True)
class DecodedCapture:
    """Per camera pixel results of :func:`decode`, each an (H, W) array.

    Attributes
    ----------
    projector_x, projector_y : float32
        Projector column and row, sub-pixel, pixel centres at integers; NaN where
        the pixel is rejected or the axis is not coded.
    modulation : float32
        Amplitude of the projected signal in grey levels (half the lit-unlit difference).
    intensity : float32
        Grey level under the white frame, or else the mean level of the coded frames.
    quality : float32
        In [0, 1]; see :func:`decode`.
    rejection : uint8
        A :class:`Rejection` code, 0 where the pixel is valid.
    coded_axes : tuple of str
        The projector axes the sequence codes.
    """

    projector_x: np.ndarray
    projector_y: np.ndarray
    modulation: np.ndarray
    intensity: np.ndarray
    quality: np.ndarray
    rejection: np.ndarray
    coded_axes: tuple[str, ...]

    @property
    def valid(self) -> np.ndarray:
        """Boolean (H, W) map of the pixels with projector coordinates."""
        return self.rejection == Rejection.VALID


@dataclass(frozen=True)
class _Tables:
    """Per-sequence lookup tables of the kernel, indexed by axis (0 = x, 1 = y)."""

    white: int
    black: int
    saturation_frames: np.ndarray  # the phase frames, whose clipping biases the phase; all frames without phase
    mean_frames: np.ndarray  # frames whose mean is the offset level, when there is no white/black pair
    axis_size: np.ndarray  # (2,)
    gray_count: np.ndarray  # (2,) Gray bits shown per axis
    gray_frame: np.ndarray  # (2, B) frame of each bit, most significant first
    gray_complement: np.ndarray  # (2, B) frame of its inverse, or -1
    gray_inverted: np.ndarray  # (2, B) 1 when gray_frame shows the inverted plane
    finest_bit: np.ndarray  # (2,)
    group_range: np.ndarray  # (3,) phase groups of axis a are group_range[a]:group_range[a + 1]
    group_start: np.ndarray  # (G + 1,) their frames are group_frames[group_start[g]:group_start[g + 1]]
    group_frames: np.ndarray
    group_cos: np.ndarray  # cos(2 pi k / N) per frame of group_frames
    group_sin: np.ndarray
    group_period: np.ndarray  # (G,) coarsest first within an axis


def _sequence_tables(sequence: Sequence) -> _Tables:
    planes = {axis: sequence.gray_planes(axis)[::-1] for axis in AXES}
    bits = max(1, max(len(p) for p in planes.values()))
    gray_frame = np.full((2, bits), -1, np.int64)
    gray_complement = np.full((2, bits), -1, np.int64)
    gray_inverted = np.zeros((2, bits), np.int64)
    finest_bit = np.zeros(2, np.int64)
    group_range, group_start, group_frames, group_cos, group_sin, group_period = [0], [0], [], [], [], []
    for a, axis in enumerate(AXES):
        for b, plane in enumerate(planes[axis]):
            gray_frame[a, b] = plane.frame
            gray_complement[a, b] = -1 if plane.complement is None else plane.complement
            gray_inverted[a, b] = int(plane.inverted)
        if planes[axis]:
            finest_bit[a] = planes[axis][-1].bit
        for group in sequence.phase_groups(axis):
            shifts = 2 * np.pi * np.arange(len(group.frames)) / len(group.frames)
            group_frames.extend(group.frames)
            group_cos.extend(np.cos(shifts))
            group_sin.extend(np.sin(shifts))
            group_period.append(group.period)
            group_start.append(len(group_frames))
        group_range.append(len(group_period))
    if sequence.phase_groups():
        mean_frames = list(sequence.phase_groups()[-1].frames)
    else:
        mean_frames = [i for axis in AXES for p in planes[axis] if p.complement is not None for i in (p.frame, p.complement)]
    white, black = sequence.white_index, sequence.black_index
    return _Tables(
        white=-1 if white is None else white,
        black=-1 if black is None else black,
        saturation_frames=np.asarray(group_frames or range(len(sequence.frames)), np.int64),
        mean_frames=np.asarray(mean_frames, np.int64),
        axis_size=np.array([sequence.projector.width, sequence.projector.height], np.int64),
        gray_count=np.array([len(planes[axis]) for axis in AXES], np.int64),
        gray_frame=gray_frame,
        gray_complement=gray_complement,
        gray_inverted=gray_inverted,
        finest_bit=finest_bit,
        group_range=np.asarray(group_range, np.int64),
        group_start=np.asarray(group_start, np.int64),
        group_frames=np.asarray(group_frames, np.int64),
        group_cos=np.asarray(group_cos, np.float64),
        group_sin=np.asarray(group_sin, np.float64),
        group_period=np.asarray(group_period, np.float64),
    )


# Hand-written numba kernel: one pass over the pixels reading the uint8/uint16 stack in place is
# what makes decoding fast and lean; vectorised numpy needs float copies of the whole stack.
@njit(parallel=True, cache=True, fastmath=False)
def _decode_kernel(frames, saturation_frames, saturation_level, white, black, mean_frames, axis_size, gray_count, gray_frame,
                   gray_complement, gray_inverted, finest_bit, group_range, group_start, group_frames, group_cos,
                   group_sin, group_period, min_intensity, min_modulation, min_quality, consistency,
                   coordinates, modulation, intensity, quality, rejection):
    n_frames, height, width = frames.shape
    for row in prange(height):
        for col in range(width):
            saturated = False
            for f in saturation_frames:
                if frames[f, row, col] >= saturation_level:
                    saturated = True
            offset = 0.0
            for f in mean_frames:
                offset += frames[f, row, col]
            if mean_frames.size > 0:
                offset /= mean_frames.size
            if white >= 0 and black >= 0:
                threshold = 0.5 * (float(frames[white, row, col]) + float(frames[black, row, col]))
            else:
                threshold = offset
            level = float(frames[white, row, col]) if white >= 0 else offset

            pixel_modulation = np.inf
            pixel_quality = 1.0
            poor_fit = False
            inconsistent = False
            for a in range(2):
                coordinates[a, row, col] = np.nan
                first_group, end_group = group_range[a], group_range[a + 1]
                if gray_count[a] == 0 and first_group == end_group:
                    continue
                reference = np.nan
                uncertainty = 0.0
                axis_modulation = 0.0
                axis_quality = 1.0
                if gray_count[a] > 0:
                    stripe_index = 0
                    binary_bit = 0
                    margin_sum = 0.0
                    margin_min = np.inf
                    for b in range(gray_count[a]):
                        value = float(frames[gray_frame[a, b], row, col])
                        if gray_complement[a, b] >= 0:
                            against = float(frames[gray_complement[a, b], row, col])
                            margin = 0.5 * abs(value - against)
                        else:
                            against = threshold
                            margin = abs(value - against)
                        gray_bit = (1 if value > against else 0) ^ gray_inverted[a, b]
                        binary_bit ^= gray_bit
                        stripe_index = 2 * stripe_index + binary_bit
                        margin_sum += margin
                        margin_min = min(margin_min, margin)
                    stripe = float(1 << finest_bit[a])
                    if stripe_index * stripe >= axis_size[a]:
                        inconsistent = True
                    reference = stripe_index * stripe + 0.5 * (stripe - 1.0)
                    uncertainty = 0.5 * stripe
                    axis_modulation = margin_sum / gray_count[a]
                    axis_quality = margin_min / axis_modulation if axis_modulation > 0 else 0.0
                for g in range(first_group, end_group):
                    period = group_period[g]
                    steps = group_start[g + 1] - group_start[g]
                    c_sum = 0.0
                    s_sum = 0.0
                    total = 0.0
                    squares = 0.0
                    for i in range(group_start[g], group_start[g + 1]):
                        value = float(frames[group_frames[i], row, col])
                        c_sum += value * group_cos[i]
                        s_sum += value * group_sin[i]
                        total += value
                        squares += value * value
                    explained = 2.0 * (c_sum * c_sum + s_sum * s_sum) / steps
                    alternating = squares - total * total / steps
                    group_quality = min(1.0, explained / alternating) if alternating > 0 else 0.0
                    if g == first_group:
                        axis_quality = group_quality
                    else:
                        axis_quality = min(axis_quality, group_quality)
                    axis_modulation = 2.0 * math.sqrt(c_sum * c_sum + s_sum * s_sum) / steps
                    phase = math.atan2(s_sum, c_sum)
                    if phase < 0:
                        phase += 2 * math.pi
                    wrapped = phase / (2 * math.pi) * period
                    if np.isnan(reference):
                        if wrapped > 0.5 * (axis_size[a] - 1 + period):
                            wrapped -= period
                        reference = wrapped
                    else:
                        unwrapped = wrapped + period * math.floor((reference - wrapped) / period + 0.5)
                        if abs(unwrapped - reference) > uncertainty + consistency * (0.5 * period - uncertainty):
                            inconsistent = True
                        reference = unwrapped
                    uncertainty = 0.0
                if first_group < end_group and axis_quality < min_quality:
                    poor_fit = True
                if reference < -0.5 or reference > axis_size[a] - 0.5:
                    inconsistent = True
                coordinates[a, row, col] = reference
                pixel_modulation = min(pixel_modulation, axis_modulation)
                pixel_quality = min(pixel_quality, axis_quality)

            if level < min_intensity:
                reason = 1
            elif saturated:
                reason = 2
            elif pixel_modulation < min_modulation:
                reason = 3
            elif poor_fit:
                reason = 4
            elif inconsistent:
                reason = 5
            else:
                reason = 0
            if reason != 0:
                coordinates[0, row, col] = np.nan
                coordinates[1, row, col] = np.nan
            modulation[row, col] = pixel_modulation
            intensity[row, col] = level
            quality[row, col] = pixel_quality
            rejection[row, col] = reason


@njit(parallel=True, cache=True, fastmath=False)
def _edge_kernel(coordinates, rejection, margin, max_jump):
    """Mark valid pixels within ``margin`` pixels of a rejected one, or beside a jump above ``max_jump``."""
    height, width = rejection.shape
    rejected = rejection != 0
    for row in prange(height):
        for col in range(width):
            if rejected[row, col]:
                continue
            edge = False
            for r in range(max(0, row - margin), min(height, row + margin + 1)):
                for c in range(max(0, col - margin), min(width, col + margin + 1)):
                    if rejected[r, c]:
                        edge = True
            for a in range(2):
                here = coordinates[a, row, col]
                if row > 0 and abs(coordinates[a, row - 1, col] - here) > max_jump:
                    edge = True
                if row + 1 < height and abs(coordinates[a, row + 1, col] - here) > max_jump:
                    edge = True
                if col > 0 and abs(coordinates[a, row, col - 1] - here) > max_jump:
                    edge = True
                if col + 1 < width and abs(coordinates[a, row, col + 1] - here) > max_jump:
                    edge = True
            if edge:
                rejection[row, col] = 6
    for row in prange(height):
        for col in range(width):
            if rejection[row, col] == 6:
                coordinates[0, row, col] = np.nan
                coordinates[1, row, col] = np.nan


def decode(
    frames: np.ndarray,
    sequence: Sequence,
    *,
    saturation_level: float | None = None,
    min_intensity: float | None = None,
    min_modulation: float | None = None,
    min_quality: float = 0.5,
    consistency: float = 0.25,
    edge_margin: int = 2,
    max_jump: float = np.inf,
) -> DecodedCapture:
    """Decode camera frames of a structured-light sequence into projector coordinates.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        One camera frame per manifest frame, in display order.
    sequence : Sequence
        What each frame encodes.
    saturation_level : float, optional
        Grey level at which the sensor saturates; default the dtype maximum (255
        or 65535; pass 4095 for a 12-bit camera in 16-bit files). It is also the
        full scale the default thresholds are relative to.
    min_intensity : float, optional
        Pixels darker than this are ``DARK``; default 2 % of full scale.
    min_modulation : float, optional
        Pixels whose signal amplitude is below this are ``LOW_MODULATION``;
        default 1.2 % of full scale (3 grey levels at 8 bits).
    min_quality : float
        Pixels with a sinusoid-fit quality below this are ``POOR_FIT``.
    consistency : float
        Fraction of the unwrapping margin by which the unwrapped phase may
        disagree with the Gray code (or the coarser period) before the pixel is
        ``INCONSISTENT``.
    edge_margin : int
        Valid pixels within this many pixels (a square neighbourhood) of a
        rejected pixel are ``EDGE``: at an object's outline a camera pixel, and
        its blur, mix the object with what lies beyond it. About twice the
        camera's blur sigma; 0 keeps them.
    max_jump : float
        Valid pixels whose projector coordinate differs from a 4-neighbour's by
        more than this many projector pixels are ``EDGE`` (both sides of a depth
        step, where mixed pixels fly between the surfaces). Infinite by default,
        since the expected gradient depends on the rig and the surface slant.

    Returns
    -------
    DecodedCapture

    Notes
    -----
    Gray code: bit plane ``b`` reads 1 where it is brighter than its inverse, or
    else than ``(white + black) / 2``, or else than the phase offset; the Gray
    bits ``g`` give the stripe index ``k`` (``binary_i = binary_{i+1} XOR g_i``),
    and with stripes ``s = 2**d`` pixels wide (``d`` the finest bit shown) the
    stripe centre is ``x_g = s k + (s - 1) / 2``.

    Phase: with ``I_k = A + B cos(phi - 2 pi k / N)``, ``C = sum I_k cos(2 pi k / N)``
    and ``S = sum I_k sin(2 pi k / N)`` give ``phi = atan2(S, C)`` and
    ``B = 2 sqrt(C^2 + S^2) / N``; the wrapped coordinate is ``x_w = P phi / 2 pi``.
    It is unwrapped against the reference ``x_r`` (the stripe centre, or the
    next coarser period's result): ``x = x_w + P round((x_r - x_w) / P)``. With
    complementary Gray code (``s <= P / 2``) the reference is within ``P / 4`` of
    the truth even when the stripe is misread at its edge, so unwrapping cannot
    jump a period [1]_. The pixel is inconsistent when ``|x - x_r| > u +
    consistency (P / 2 - u)``, ``u = s / 2`` (0 against a coarser period).

    ``quality`` is the fraction of the samples' AC energy explained by the
    sinusoid, ``2 (C^2 + S^2) / N / sum (I_k - A)^2`` (the smallest over the
    periods and axes); for axes coded by Gray code alone it is the smallest
    plane margin over the mean margin, and ``POOR_FIT`` does not apply.
    ``modulation`` is ``B`` of the finest period, or the mean Gray plane margin
    ``|I - I_inverse| / 2`` or ``|I - threshold|``.

    References
    ----------
    .. [1] Q. Zhang, X. Su, L. Xiang, X. Sun, "3-D shape measurement based on
       complementary Gray-code light", Optics and Lasers in Engineering 50(4), 574-579 (2012).
    """
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"Frames must be a (F, H, W) stack; got an array of shape {frames.shape}.")
    if frames.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"Frames must be uint8 or uint16; got {frames.dtype}.")
    if frames.shape[0] != len(sequence.frames):
        raise ValueError(f"The sequence has {len(sequence.frames)} frames but {frames.shape[0]} were given.")
    if not 0 <= consistency <= 1:
        raise ValueError(f"consistency must be between 0 and 1; got {consistency}.")
    if edge_margin < 0:
        raise ValueError(f"edge_margin must be a non-negative number of pixels; got {edge_margin}.")
    full_scale = float(np.iinfo(frames.dtype).max if saturation_level is None else saturation_level)
    min_intensity = 0.02 * full_scale if min_intensity is None else min_intensity
    min_modulation = 0.012 * full_scale if min_modulation is None else min_modulation
    tables = _sequence_tables(sequence)
    height, width = frames.shape[1:]
    coordinates = np.empty((2, height, width), np.float32)
    modulation = np.empty((height, width), np.float32)
    intensity = np.empty((height, width), np.float32)
    quality = np.empty((height, width), np.float32)
    rejection = np.empty((height, width), np.uint8)
    _decode_kernel(
        np.ascontiguousarray(frames), tables.saturation_frames, full_scale, tables.white, tables.black, tables.mean_frames, tables.axis_size,
        tables.gray_count, tables.gray_frame, tables.gray_complement, tables.gray_inverted, tables.finest_bit,
        tables.group_range, tables.group_start, tables.group_frames, tables.group_cos, tables.group_sin,
        tables.group_period, float(min_intensity), float(min_modulation), float(min_quality), float(consistency),
        coordinates, modulation, intensity, quality, rejection,
    )
    if edge_margin > 0 or np.isfinite(max_jump):
        _edge_kernel(coordinates, rejection, int(edge_margin), float(max_jump))
    return DecodedCapture(
        projector_x=coordinates[0],
        projector_y=coordinates[1],
        modulation=modulation,
        intensity=intensity,
        quality=quality,
        rejection=rejection,
        coded_axes=sequence.coded_axes,
    )
