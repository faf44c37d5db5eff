"""Decoding a structured-light capture: sub-pixel projector coordinates per camera pixel.

Any sequence a manifest can describe is decoded in one pass over the pixels:
Gray-code planes (against their inverse, the white/black mid level or the
phase offset), N-step phase shifting at one or several periods, and their
combination, with the phase unwrapped against the Gray-code stripe centre.
The pass is plain numpy and OpenCV over bands of rows on a small thread pool
(``row_bands``); only the sub-pixel interpolation of Gray-code-only axes
(``gray_subpixel``) is a numba kernel, imported when such a capture is decoded.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np

from services.formats.sequence import AXES, Sequence
from services.structured_light.row_bands import map_row_bands
from services.structured_light import defaults


class Rejection(enum.IntEnum):
    """Why a camera pixel has no projector coordinate (the ``rejection`` map); checked in this order."""

    VALID = 0
    DARK = 1  #: intensity below ``min_intensity``: outside the projector's light or too dark
    SATURATED = 2  #: a phase frame (any frame if none) reaches ``saturation_level``: clipping biases the phase
    LOW_MODULATION = 3  #: the projected signal is below ``min_modulation``: projector shadow, glare, dark surface
    POOR_FIT = 4  #: ``quality`` below ``min_quality``: the samples are not one sinusoid (mixed or moving surface)
    INCONSISTENT = 5  #: Gray code and phase (or two phase periods) disagree, or the code is out of range
    EDGE = 6  #: next to a rejected pixel or across a coordinate jump: a camera pixel mixing two surfaces
    GLOW_SATURATED = 7  #: a hot part's own glow saturates the pattern (``glow.decode_glowing`` only)
    GLOW_NOISE = 8  #: the pattern is below what the glow's shot noise allows (``glow.decode_glowing`` only)
    INDIRECT = 9  #: fringe visibility far below the capture's direct light: inter-reflections, scattering


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
    """Per-sequence lookup tables of the band pass (:func:`_decode_rows`), indexed by axis (0 = x, 1 = y)."""

    white: int
    black: int
    mean_frames: np.ndarray  # Gray planes and inverses whose mean is the offset level (no phase, no white/black pair)
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
    white, black = sequence.white_index, sequence.black_index
    mean_frames = [i for axis in AXES for p in planes[axis] if p.complement is not None for i in (p.frame, p.complement)]
    if white is not None and black is not None:
        mean_frames = []  # the references give both the threshold and the intensity
    return _Tables(
        white=-1 if white is None else white,
        black=-1 if black is None else black,
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


def _above32(value: float) -> np.float32:
    """The least float32 not below ``value``: ``x < value`` is ``x < _above32(value)`` for every float32 x."""
    rounded = np.float32(value)
    return rounded if rounded >= value else np.nextafter(rounded, np.float32(np.inf))


def _below32(value: float) -> np.float32:
    """The greatest float32 not above ``value``: ``x > value`` is ``x > _below32(value)`` for every float32 x."""
    rounded = np.float32(value)
    return rounded if rounded <= value else np.nextafter(rounded, np.float32(-np.inf))


def _level_limit(dtype: np.dtype, value: float):
    """``value`` as a scalar of the frames' dtype that compares with the frames as ``value`` itself does
    (``x >= value`` is ``x >= limit``, and ``x < value`` is ``x < limit``): rounded up for integers, at most
    one above the dtype's maximum (then held in a wider type)."""
    if dtype == np.float64:
        return value
    if dtype == np.float32:
        return _above32(value)
    return min(math.ceil(value), np.iinfo(dtype).max + 1)


# Rejection codes by precedence: a pixel gets the code of the highest-ranked condition it meets.
_PRECEDENCE = (Rejection.INCONSISTENT, Rejection.POOR_FIT, Rejection.LOW_MODULATION, Rejection.SATURATED,
               Rejection.DARK)
_RANKED_CODE = np.zeros(256, np.uint8)  # rank (1 for the lowest) -> code
_RANKED_CODE[1:len(_PRECEDENCE) + 1] = _PRECEDENCE
_RANKED_SCALE = np.ones(256, np.float32)  # rank -> 1 for a valid pixel, NaN for a rejected one
_RANKED_SCALE[1:] = np.nan


@dataclass(frozen=True)
class _DecodeInputs:
    """What every band of rows reads (see :func:`decode`): the frames, the sequence's tables and the
    thresholds, in the frames' grey levels."""

    frames: np.ndarray  # (F, H, W), C-contiguous
    tables: _Tables
    saturation_level: float
    min_intensity: float
    min_modulation: float
    min_quality: float
    consistency: float


@dataclass(frozen=True)
class _DecodeMaps:
    """The per-pixel outputs every band writes its rows of."""

    coordinates: np.ndarray  # (2, H, W) float32: projector x and y
    modulation: np.ndarray  # (H, W) float32
    intensity: np.ndarray  # (H, W) float32
    quality: np.ndarray  # (H, W) float32
    rejection: np.ndarray  # (H, W) uint8

    @classmethod
    def empty(cls, height: int, width: int) -> _DecodeMaps:
        return cls(np.empty((2, height, width), np.float32), *(np.empty((height, width), np.float32) for _ in range(3)),
                   np.empty((height, width), np.uint8))


@dataclass(frozen=True)
class _PhaseSums:
    """One phase group's sums over a band's pixels: ``C`` and ``S`` (see :func:`decode`), and the sum and the
    sum of squares of its samples."""

    cos: np.ndarray
    sin: np.ndarray
    total: np.ndarray
    squares: np.ndarray


@dataclass
class _Band:
    """A band of rows being decoded: its frames (F, rows, W), the float type its sums are made in, and the
    pixels found ``POOR_FIT`` and ``INCONSISTENT`` so far (set in place by each axis)."""

    frames: np.ndarray
    work: type
    poor_fit: np.ndarray
    inconsistent: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.frames.shape[1:]


@dataclass(frozen=True)
class _AxisDecoding:
    """One coded axis of a band: the projector coordinate (unscaled by the rejections), its modulation and
    quality."""

    coordinate: np.ndarray
    modulation: np.ndarray
    quality: np.ndarray


# Plain numpy and OpenCV, a band of rows at a time on the row-band pool (both release the GIL): the
# phase sums accumulate from the uint8/uint16 frames one frame at a time (cv2.accumulate and
# accumulateSquare read them without a float copy of the stack), and a band's temporaries, about
# 256 kB each, stay in the CPU cache. uint8 samples are summed in float32, where sums and sums of
# squares are exact (integers below 2**24); wider samples in float64.
def _decode_rows(inputs: _DecodeInputs, maps: _DecodeMaps, rows: slice) -> None:
    """Decode the camera rows ``rows`` into ``maps`` (see :func:`decode`)."""
    frames, tables = inputs.frames, inputs.tables
    band = frames[:, rows]
    band = _Band(band, np.float32 if frames.dtype == np.uint8 else np.float64, np.zeros(band.shape[1:], bool),
                 np.zeros(band.shape[1:], bool))
    saturated = _saturated(band, tables, inputs.saturation_level)
    sums = _phase_sums(band, tables)
    threshold, level = _threshold_and_level(band, tables, sums)
    axes = [_decode_axis(band, tables, sums, threshold, axis, inputs) for axis in range(2)]
    _write_band(maps, rows, band, axes, level, saturated, inputs)


def _saturated(band: _Band, tables: _Tables, saturation_level: float) -> np.ndarray:
    """Clipping: the pixels where any phase frame (any frame without phase) reaches the saturation level."""
    clipping_frames = tables.group_frames if tables.group_period.size > 0 else range(band.frames.shape[0])
    brightest = band.frames[clipping_frames[0]].copy()
    for f in clipping_frames[1:]:
        np.maximum(brightest, band.frames[f], out=brightest)
    return brightest >= _level_limit(band.frames.dtype, saturation_level)


def _phase_sums(band: _Band, tables: _Tables) -> list[_PhaseSums]:
    """Each phase group's sums, in the tables' order."""
    work, sums = band.work, []
    sample, opposite = np.empty(band.shape, work), np.empty(band.shape, work)
    for g in range(tables.group_period.size):
        c_sum, s_sum, total, squares = (np.zeros(band.shape, work) for _ in range(4))
        first, end = tables.group_start[g], tables.group_start[g + 1]
        # With an even number of steps, the shift half a period on negates the cosine and sine: the
        # difference of the two frames enters C and S once, halving the multiply-adds.
        half = (end - first) // 2 if (end - first) % 2 == 0 else end - first
        for i in range(first, first + half):
            np.copyto(sample, band.frames[tables.group_frames[i]])
            if half < end - first:
                np.copyto(opposite, band.frames[tables.group_frames[i + half]])
                sample -= opposite
            # numpy's multiply and add, not cv2.scaleAdd: its vector body fuses the multiply-add and its
            # scalar tail does not, so the last bit would depend on where the allocator put the band.
            c_sum += np.multiply(sample, tables.group_cos[i].astype(work), out=opposite)
            s_sum += np.multiply(sample, tables.group_sin[i].astype(work), out=opposite)
        for i in range(first, end):
            cv2.accumulate(band.frames[tables.group_frames[i]], total)
            cv2.accumulateSquare(band.frames[tables.group_frames[i]], squares)
        sums.append(_PhaseSums(c_sum, s_sum, total, squares))
    return sums


def _threshold_and_level(band: _Band, tables: _Tables, sums: list[_PhaseSums]
                         ) -> tuple[np.ndarray | None, np.ndarray]:
    """The level a Gray plane without its inverse is compared with (the white and black frames' mean, or
    the offset of the finest phase group, or the mean of the complementary Gray planes; None without any),
    and each pixel's intensity (the white frame, or the mean of every phase frame, or that offset)."""
    n_groups = tables.group_period.size
    references = tables.white >= 0 and tables.black >= 0
    offset = None
    if n_groups > 0 and not references:
        offset = sums[-1].total / (tables.group_start[n_groups] - tables.group_start[n_groups - 1])
    elif n_groups == 0:
        offset = np.zeros(band.shape, band.work)
        for f in tables.mean_frames:
            cv2.accumulate(band.frames[f], offset)
        if tables.mean_frames.size > 0:
            offset /= tables.mean_frames.size
    threshold = offset
    if references:
        threshold = np.zeros(band.shape, band.work)
        cv2.accumulate(band.frames[tables.white], threshold)
        cv2.accumulate(band.frames[tables.black], threshold)
        threshold *= 0.5
    if tables.white >= 0:
        level = band.frames[tables.white]
    elif n_groups > 0:
        # The intensity without a white frame: the mean of every phase frame, the least noisy
        # offset (a board image with a twelfth of one frame's noise variance for SLStudio's 12).
        level = sums[0].total.copy()
        for g in range(1, n_groups):
            level += sums[g].total
        level /= tables.group_start[n_groups]
    else:
        level = offset
    return threshold, level


def _decode_axis(band: _Band, tables: _Tables, sums: list[_PhaseSums], threshold: np.ndarray | None, axis: int,
                 inputs: _DecodeInputs) -> _AxisDecoding | None:
    """The Gray-code stripe centre of ``axis``, refined by its phase groups coarsest first; None when the
    sequence does not code it. Marks the band's pixels ``POOR_FIT`` and ``INCONSISTENT``."""
    first_group, end_group = tables.group_range[axis], tables.group_range[axis + 1]
    if tables.gray_count[axis] == 0 and first_group == end_group:
        return None
    axis_size = float(tables.axis_size[axis])
    decoded, uncertainty = None, 0.0
    if tables.gray_count[axis] > 0:
        decoded, uncertainty = _gray_stripes(band, tables, threshold, axis, gray_only=first_group == end_group)
    if first_group < end_group:
        decoded = _unwrapped_phase(band, tables, sums, axis, decoded, uncertainty, inputs.consistency)
        min_quality = _above32(inputs.min_quality) if decoded.quality.dtype == np.float32 else inputs.min_quality
        band.poor_fit |= decoded.quality < min_quality
    band.inconsistent |= decoded.coordinate < np.float32(-0.5)
    band.inconsistent |= decoded.coordinate > _below32(axis_size - 0.5)
    return decoded


def _gray_stripes(band: _Band, tables: _Tables, threshold: np.ndarray | None, axis: int, gray_only: bool
                  ) -> tuple[_AxisDecoding, float]:
    """The stripe centre of each pixel from the axis's Gray planes, and its uncertainty (half a stripe).
    The plane margins give the modulation and the quality of an axis coded by Gray code ``gray_only``
    (else the phase's replace them: both are then None)."""
    work, shape = band.work, band.shape
    gray_count = int(tables.gray_count[axis])
    # The stripe index, built most significant bit first: binary_i = binary_{i+1} XOR gray_i.
    stripe_index = np.zeros(shape, np.uint8 if gray_count <= 8 else np.uint16 if gray_count <= 16 else np.int64)
    binary = np.zeros(shape, np.uint8)
    bit = np.empty(shape, bool)
    if gray_only:
        margin_sum = np.zeros(shape, work)
        margin_min = np.full(shape, np.inf, work)
    for b in range(gray_count):
        plane = band.frames[tables.gray_frame[axis, b]]
        other = band.frames[tables.gray_complement[axis, b]] if tables.gray_complement[axis, b] >= 0 else threshold
        # The bit XOR inverted: the plane above its complement or threshold, or for an inverted plane not.
        (np.less_equal if tables.gray_inverted[axis, b] else np.greater)(plane, other, out=bit)
        np.bitwise_xor(binary, bit.view(np.uint8), out=binary)
        np.add(stripe_index, stripe_index, out=stripe_index)
        np.add(stripe_index, binary, out=stripe_index, casting="unsafe")
        if gray_only:
            margin = np.abs(np.subtract(plane, other, dtype=work))
            if tables.gray_complement[axis, b] >= 0:
                margin *= 0.5
            margin_sum += margin
            np.minimum(margin_min, margin, out=margin_min)
    stripe = float(1 << int(tables.finest_bit[axis]))
    centre = stripe_index.astype(np.float32)
    centre *= np.float32(stripe)
    band.inconsistent |= centre >= float(tables.axis_size[axis])  # stripe indices are exact in float32
    centre += np.float32(0.5 * (stripe - 1.0))
    modulation = quality = None
    if gray_only:
        modulation = margin_sum / gray_count
        quality = np.divide(margin_min, modulation, out=np.zeros(shape, work), where=modulation > 0)
    return _AxisDecoding(centre, modulation, quality), 0.5 * stripe


def _unwrapped_phase(band: _Band, tables: _Tables, sums: list[_PhaseSums], axis: int,
                     stripes: _AxisDecoding | None, uncertainty: float, consistency: float) -> _AxisDecoding:
    """The axis's phase groups, coarsest first, each unwrapped against the reference before it (the
    stripe centre, or the coarser period's coordinate; the first without Gray code is taken as it is);
    the finest period's modulation and the least quality over the groups."""
    axis_size = float(tables.axis_size[axis])
    first_group, end_group = tables.group_range[axis], tables.group_range[axis + 1]
    reference = None if stripes is None else stripes.coordinate
    for g in range(first_group, end_group):
        c_sum, s_sum, total, squares = (sums[g].cos, sums[g].sin, sums[g].total, sums[g].squares)
        period = float(tables.group_period[g])
        steps = int(tables.group_start[g + 1] - tables.group_start[g])
        tolerance = uncertainty + consistency * (0.5 * period - uncertainty)
        if band.work == np.float32 and steps > 16:  # beyond, the float32 sums of uint8 samples are no longer exact
            c_sum, s_sum, total, squares = (np.asarray(x, np.float64) for x in (c_sum, s_sum, total, squares))
        energy = np.square(c_sum)  # C^2 + S^2 (not cv2.magnitude, which also fuses multiply-adds)
        energy += np.square(s_sum)
        amplitude = np.sqrt(energy)
        # steps * sum (I - A)^2, exact for uint8 samples; the sinusoid's share of it, 0 without any.
        alternating = squares * float(steps)
        alternating -= np.square(total)
        np.copyto(alternating, np.inf, where=alternating <= 0)
        group_quality = energy
        group_quality /= alternating
        group_quality *= 2.0
        np.minimum(group_quality, 1.0, out=group_quality)
        quality = group_quality if g == first_group else np.minimum(quality, group_quality)
        modulation = amplitude
        modulation *= 2.0 / steps
        wrapped = np.arctan2(s_sum, c_sum, dtype=np.float32)  # in (-pi, pi]
        negative = wrapped < 0
        wrapped *= np.float32(period / (2 * np.pi))
        wrapped += negative * np.float32(period)
        if reference is not None:
            turns = reference - wrapped
            turns *= np.float32(1 / period)
            turns += np.float32(0.5)
            np.floor(turns, out=turns)
            turns *= np.float32(period)
            wrapped += turns  # unwrapped
            np.subtract(wrapped, reference, out=turns)
            np.abs(turns, out=turns)
            band.inconsistent |= turns > _below32(tolerance)
        else:
            np.subtract(wrapped, np.float32(period), out=wrapped,
                        where=wrapped > _below32(0.5 * (axis_size - 1 + period)))
        reference = wrapped
        uncertainty = 0.0
    return _AxisDecoding(reference, modulation, quality)


def _write_band(maps: _DecodeMaps, rows: slice, band: _Band, axes: list[_AxisDecoding | None], level: np.ndarray,
                saturated: np.ndarray, inputs: _DecodeInputs) -> None:
    """Each pixel's rejection code (the first reason that applies), its coordinates (NaN where rejected or
    not coded), modulation and quality (the least over the axes) and intensity, into the band's rows."""
    coded = [decoded for decoded in axes if decoded is not None]
    modulation, quality = coded[0].modulation, coded[0].quality
    for decoded in coded[1:]:
        modulation = np.minimum(modulation, decoded.modulation)
        quality = np.minimum(quality, decoded.quality)
    # The code of the first reason that applies: the highest rank of those met, through a table.
    low_modulation = modulation < (_above32(inputs.min_modulation) if modulation.dtype == np.float32
                                   else inputs.min_modulation)
    dark = level < _level_limit(level.dtype, inputs.min_intensity)
    rank = band.inconsistent.view(np.uint8).copy()
    for r, met in enumerate((band.poor_fit, low_modulation, saturated, dark), start=2):
        np.maximum(rank, np.multiply(met.view(np.uint8), np.uint8(r)), out=rank)
    cv2.LUT(rank, _RANKED_CODE, dst=maps.rejection[rows])
    scale = cv2.LUT(rank, _RANKED_SCALE)  # NaN where rejected
    for a, decoded in enumerate(axes):
        if decoded is None:
            maps.coordinates[a, rows] = np.nan
        else:
            np.multiply(decoded.coordinate, scale, out=maps.coordinates[a, rows])
    maps.modulation[rows] = modulation
    maps.intensity[rows] = level
    maps.quality[rows] = quality


def _reject_edges(coordinates: np.ndarray, rejection: np.ndarray, margin: int, max_jump: float) -> None:
    """Mark valid pixels within ``margin`` pixels of a rejected one, or beside a jump above ``max_jump``,
    ``EDGE``, in place."""
    if margin > 0:
        rejected = np.not_equal(rejection, Rejection.VALID).view(np.uint8)
        edge = cv2.dilate(rejected, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)).view(bool)
    else:
        edge = np.zeros(rejection.shape, bool)
    if np.isfinite(max_jump):
        limit = np.float64(max_jump)
        for axis in coordinates:  # NaN beside a rejected pixel compares False: no jump
            step = np.abs(np.diff(axis, axis=1)) > limit
            edge[:, :-1] |= step
            edge[:, 1:] |= step
            step = np.abs(np.diff(axis, axis=0)) > limit
            edge[:-1] |= step
            edge[1:] |= step
    edge &= rejection == Rejection.VALID
    rejection[edge] = Rejection.EDGE
    coordinates[:, edge] = np.nan  # after the jump test, which reads the neighbours' coordinates


def _interpolate_gray_only_axes(frames: np.ndarray, sequence: Sequence, coordinates: np.ndarray,
                                rejection: np.ndarray) -> None:
    """Replace the stripe centres of Gray-code-only axes by ``gray_subpixel``'s coordinates, in place;
    pixels it cannot interpolate become ``INCONSISTENT``."""
    gray_only = [a for a, axis in enumerate(AXES) if sequence.gray_planes(axis) and not sequence.phase_groups(axis)]
    if not gray_only:
        return
    # Imported here: it is a numba kernel, and only Gray-code-only captures need it.
    from services.structured_light.gray_subpixel import gray_subpixel

    for a in gray_only:
        coordinates[a] = gray_subpixel(frames, sequence, AXES[a], coordinates[a])
        lost = (rejection == Rejection.VALID) & np.isnan(coordinates[a])
        rejection[lost] = Rejection.INCONSISTENT
        coordinates[:, lost] = np.nan


def _reject_indirect(coordinates: np.ndarray, modulation: np.ndarray, intensity: np.ndarray, rejection: np.ndarray,
                     max_indirect: float) -> None:
    """Mark valid pixels whose visibility B / intensity says indirect light exceeds ``max_indirect`` times the
    direct light (see :func:`decode`)."""
    valid = rejection == Rejection.VALID
    if not valid.any():
        return
    visibility = np.where(intensity > 0, modulation / np.maximum(intensity, 1e-6), 0.0)
    bright = valid & (modulation >= np.median(modulation[valid]))
    direct_visibility = float(np.median(visibility[bright]))
    indirect = valid & (visibility * (1.0 + max_indirect) < direct_visibility)
    rejection[indirect] = Rejection.INDIRECT
    coordinates[:, indirect] = np.nan


def decode(
    frames: np.ndarray,
    sequence: Sequence,
    *,
    saturation_level: float | None = None,
    min_intensity: float | None = None,
    min_modulation: float | None = None,
    min_quality: float = 0.5,
    consistency: float = defaults.CONSISTENCY,
    edge_margin: int = 3,
    max_jump: float = np.inf,
    gray_boundaries: bool = True,
    max_indirect: float = defaults.MAX_INDIRECT,
) -> DecodedCapture:
    """Decode camera frames of a structured-light sequence into projector coordinates.

    Parameters
    ----------
    frames : (F, H, W) uint8, uint16 or float32 array
        One camera frame per manifest frame, in display order (float32: grey levels with an offset
        removed, as ``glow.decode_glowing`` passes them, with ``saturation_level`` given).
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
        its blur, mix the object with what lies beyond it. About three times the
        camera's blur sigma; 0 keeps them.
    max_jump : float
        Valid pixels whose projector coordinate differs from a 4-neighbour's by
        more than this many projector pixels are ``EDGE`` (both sides of a depth
        step, where mixed pixels fly between the surfaces). Infinite by default,
        since the expected gradient depends on the rig and the surface slant.
    gray_boundaries : bool
        For axes coded by Gray code alone, interpolate the coordinate between the stripe boundaries
        located in the image (``gray_subpixel``); pixels without boundaries on both sides (or one side,
        within a stripe) are then ``INCONSISTENT``. False gives the stripe centres.
    max_indirect : float
        Valid pixels of a phase-coded capture whose indirect light is estimated at
        more than this multiple of their direct light are ``INDIRECT`` (see Notes):
        inter-reflections in concavities, subsurface scattering. Infinite (off) by
        default: unmodulated light from other sources (ambient light, the glow of a
        hot part) lowers the visibility in the same way without biasing the phase.

    Returns
    -------
    DecodedCapture

    Notes
    -----
    Gray code: bit plane ``b`` reads 1 where it is brighter than its inverse, or
    else than ``(white + black) / 2``, or else than the phase offset; the Gray
    bits ``g`` give the stripe index ``k`` (``binary_i = binary_{i+1} XOR g_i``),
    and with stripes ``s = 2**d`` pixels wide (``d`` the finest bit shown) the
    stripe centre is ``x_g = s k + (s - 1) / 2``. Axes coded by Gray code alone are then refined to
    sub-pixel by ``gray_subpixel``: the coordinate is interpolated between the stripe boundaries, located
    where the flipping bit's plane crosses its inverse (or threshold) between two camera pixels.

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

    Indirect light: light that reaches a pixel after another bounce sums the
    fringes over many projector pixels, so at a fine period it is unmodulated [2]_
    while it biases the phase of coarse periods. With direct light D and indirect
    light G, the fringe visibility ``V = B / intensity`` is ``V_0 D / (D + G)``,
    ``V_0`` that of direct light alone, estimated as the median visibility of the
    valid pixels brighter (in ``B``) than the median. A pixel is ``INDIRECT`` when
    ``G / D = V_0 / V - 1 > max_indirect``.

    References
    ----------
    .. [1] Q. Zhang, X. Su, L. Xiang, X. Sun, "3-D shape measurement based on
       complementary Gray-code light", Optics and Lasers in Engineering 50(4), 574-579 (2012).
    .. [2] S. K. Nayar, G. Krishnan, M. D. Grossberg, R. Raskar, "Fast separation of direct and
       global components of a scene using high frequency illumination", ACM TOG 25(3), 935-944 (2006).
    """
    frames = np.asarray(frames)
    if frames.ndim != 3:
        raise ValueError(f"Frames must be a (F, H, W) stack; got an array of shape {frames.shape}.")
    if frames.dtype not in (np.uint8, np.uint16, np.float32):
        raise ValueError(f"Frames must be uint8, uint16 or float32; got {frames.dtype}.")
    if frames.dtype == np.float32 and saturation_level is None:
        raise ValueError("Float32 frames (offset-free grey levels) need an explicit saturation_level.")
    if frames.shape[0] != len(sequence.frames):
        raise ValueError(f"The sequence has {len(sequence.frames)} frames but {frames.shape[0]} were given.")
    if not 0 <= consistency <= 1:
        raise ValueError(f"consistency must be between 0 and 1; got {consistency}.")
    if edge_margin < 0:
        raise ValueError(f"edge_margin must be a non-negative number of pixels; got {edge_margin}.")
    if not max_indirect > 0:
        raise ValueError(f"max_indirect must be a positive ratio of indirect to direct light; got {max_indirect}.")
    full_scale = float(np.iinfo(frames.dtype).max if saturation_level is None else saturation_level)
    min_intensity = 0.02 * full_scale if min_intensity is None else min_intensity
    min_modulation = 0.012 * full_scale if min_modulation is None else min_modulation
    inputs = _DecodeInputs(np.ascontiguousarray(frames), _sequence_tables(sequence), full_scale, float(min_intensity),
                           float(min_modulation), float(min_quality), float(consistency))
    height, width = frames.shape[1:]
    maps = _DecodeMaps.empty(height, width)
    map_row_bands(partial(_decode_rows, inputs, maps), height, width)
    coordinates, modulation, intensity, quality, rejection = (maps.coordinates, maps.modulation, maps.intensity,
                                                              maps.quality, maps.rejection)
    if np.isfinite(max_indirect) and sequence.phase_groups():
        _reject_indirect(coordinates, modulation, intensity, rejection, max_indirect)
    if edge_margin > 0 or np.isfinite(max_jump):
        _reject_edges(coordinates, rejection, int(edge_margin), float(max_jump))
    if gray_boundaries:
        _interpolate_gray_only_axes(frames, sequence, coordinates, rejection)
    return DecodedCapture(
        projector_x=coordinates[0],
        projector_y=coordinates[1],
        modulation=modulation,
        intensity=intensity,
        quality=quality,
        rejection=rejection,
        coded_axes=sequence.coded_axes,
    )
