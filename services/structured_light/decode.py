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
from numba import get_num_threads, njit, prange

from services.formats.sequence import AXES, Sequence
from services.numba_options import SAFE_FASTMATH
from services.structured_light.gray_subpixel import gray_subpixel


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
    """Per-sequence lookup tables of the kernel, indexed by axis (0 = x, 1 = y)."""

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


# Abramowitz and Stegun 4.4.49: atan(a) = a (1 + sum_k c_k a^2k) on [0, 1], |error| <= 2e-8 rad.
_ATAN_COEFFICIENTS = (-0.3333314528, 0.1999355085, -0.1420889944, 0.1065626393, -0.0752896400, 0.0429096138,
                      -0.0161657367, 0.0028662257)


@njit(cache=True, inline="always", fastmath=False)
def _polynomial_atan2(y, x):
    """atan2(y, x) in (-pi, pi] to 2e-8 rad, branch-free so that the column loops vectorise.

    libm's atan2 is a scalar call that costs half the decoding time; 2e-8 rad is 5e-8 px at a
    16-pixel period.
    """
    ax, ay = abs(x), abs(y)
    high, low = max(ax, ay), min(ax, ay)
    a = low / high if high > 0 else 0.0
    s = a * a
    c = _ATAN_COEFFICIENTS
    r = (((((((c[7] * s + c[6]) * s + c[5]) * s + c[4]) * s + c[3]) * s + c[2]) * s + c[1]) * s + c[0]) * s
    r = (r + 1.0) * a
    r = 0.5 * math.pi - r if ay > ax else r
    r = math.pi - r if x < 0 else r
    return -r if y < 0 else r


# Hand-written numba kernels: one pass over the rows reading the uint8/uint16 stack in place, with
# row buffers so the inner loops over columns vectorise; numpy would need float copies of the stack.
@njit(parallel=True, cache=True, fastmath=SAFE_FASTMATH)
def _decode_kernel(frames, saturation_level, white, black, mean_frames, axis_size, gray_count,
                   gray_frame, gray_complement, gray_inverted, finest_bit, group_range, group_start, group_frames,
                   group_cos, group_sin, group_period, min_intensity, min_modulation, min_quality, consistency,
                   chunks, coordinates, modulation, intensity, quality, rejection):
    height, width = frames.shape[1], frames.shape[2]
    n_groups = group_period.size
    for chunk in prange(chunks):
        # Row buffers allocated once per chunk of rows: allocating them per row cost a tenth of the kernel.
        saturated = np.empty(width, np.bool_)
        c_sum = np.empty((n_groups, width))
        s_sum = np.empty((n_groups, width))
        total = np.empty((n_groups, width))
        squares = np.empty((n_groups, width))
        offset = np.empty(width)
        mean_level = np.empty(width)
        mid_level = np.empty(width)
        white_level = np.empty(width)
        pixel_modulation = np.empty(width)
        pixel_quality = np.empty(width)
        poor_fit = np.empty(width, np.bool_)
        inconsistent = np.empty(width, np.bool_)
        reference = np.empty(width)
        axis_modulation = np.empty(width)
        axis_quality = np.empty(width)
        stripe_index = np.empty(width, np.int32)
        binary = np.empty(width, np.int32)
        margin_sum = np.empty(width)
        margin_min = np.empty(width)
        for row in range(chunk * height // chunks, (chunk + 1) * height // chunks):
            # Phase sums first: the same pass over the phase frames finds clipping and the offset level.
            saturated[:] = False
            c_sum[:] = 0.0
            s_sum[:] = 0.0
            total[:] = 0.0
            squares[:] = 0.0
            for g in range(n_groups):
                first, end = group_start[g], group_start[g + 1]
                # Four frames per pass over the row: a quarter of the accumulator loads and stores.
                for i in range(first, end - 3, 4):
                    p0, p1 = frames[group_frames[i], row], frames[group_frames[i + 1], row]
                    p2, p3 = frames[group_frames[i + 2], row], frames[group_frames[i + 3], row]
                    c0, c1, c2, c3 = group_cos[i], group_cos[i + 1], group_cos[i + 2], group_cos[i + 3]
                    s0, s1, s2, s3 = group_sin[i], group_sin[i + 1], group_sin[i + 2], group_sin[i + 3]
                    for col in range(width):
                        v0, v1, v2, v3 = float(p0[col]), float(p1[col]), float(p2[col]), float(p3[col])
                        c_sum[g, col] += v0 * c0 + v1 * c1 + v2 * c2 + v3 * c3
                        s_sum[g, col] += v0 * s0 + v1 * s1 + v2 * s2 + v3 * s3
                        total[g, col] += v0 + v1 + v2 + v3
                        squares[g, col] += v0 * v0 + v1 * v1 + v2 * v2 + v3 * v3
                        saturated[col] |= max(max(v0, v1), max(v2, v3)) >= saturation_level
                for i in range(first + (end - first) // 4 * 4, end):
                    samples = frames[group_frames[i], row]
                    cosine, sine = group_cos[i], group_sin[i]
                    for col in range(width):
                        value = float(samples[col])
                        c_sum[g, col] += value * cosine
                        s_sum[g, col] += value * sine
                        total[g, col] += value
                        squares[g, col] += value * value
                        saturated[col] |= value >= saturation_level
            if n_groups > 0:
                steps = group_start[n_groups] - group_start[n_groups - 1]
                for col in range(width):
                    offset[col] = total[n_groups - 1, col] / steps
                # The intensity without a white frame: the mean of every phase frame, the least noisy
                # offset (a board image with a twelfth of one frame's noise variance for SLStudio's 12).
                mean_level[:] = 0.0
                for g in range(n_groups):
                    for col in range(width):
                        mean_level[col] += total[g, col]
                mean_level /= group_start[n_groups]
            else:
                for f in range(frames.shape[0]):
                    samples = frames[f, row]
                    for col in range(width):
                        saturated[col] |= samples[col] >= saturation_level
                offset[:] = 0.0
                for f in mean_frames:
                    samples = frames[f, row]
                    for col in range(width):
                        offset[col] += samples[col]
                if mean_frames.size > 0:
                    offset /= mean_frames.size
            threshold = offset
            if white >= 0 and black >= 0:
                threshold = mid_level
                for col in range(width):
                    threshold[col] = 0.5 * (float(frames[white, row, col]) + float(frames[black, row, col]))
            level = mean_level if n_groups > 0 else offset
            if white >= 0:
                level = white_level
                for col in range(width):
                    level[col] = frames[white, row, col]

            pixel_modulation[:] = np.inf
            pixel_quality[:] = 1.0
            poor_fit[:] = False
            inconsistent[:] = False
            for a in range(2):
                first_group, end_group = group_range[a], group_range[a + 1]
                if gray_count[a] == 0 and first_group == end_group:
                    coordinates[a, row] = np.nan
                    continue
                referenced = False
                uncertainty = 0.0
                if gray_count[a] > 0:
                    gray_only = first_group == end_group  # the plane margins are then modulation and quality
                    stripe_index[:] = 0
                    binary[:] = 0
                    margin_sum[:] = 0.0
                    margin_min[:] = np.inf
                    for b in range(gray_count[a]):
                        plane = frames[gray_frame[a, b], row]
                        inverted = np.int32(gray_inverted[a, b])
                        if gray_complement[a, b] >= 0:
                            complement = frames[gray_complement[a, b], row]
                            for col in range(width):
                                binary[col] ^= np.int32(plane[col] > complement[col]) ^ inverted
                                stripe_index[col] = 2 * stripe_index[col] + binary[col]
                            if gray_only:
                                for col in range(width):
                                    margin = 0.5 * abs(float(plane[col]) - float(complement[col]))
                                    margin_sum[col] += margin
                                    margin_min[col] = min(margin_min[col], margin)
                        else:
                            for col in range(width):
                                binary[col] ^= np.int32(plane[col] > threshold[col]) ^ inverted
                                stripe_index[col] = 2 * stripe_index[col] + binary[col]
                            if gray_only:
                                for col in range(width):
                                    margin = abs(plane[col] - threshold[col])
                                    margin_sum[col] += margin
                                    margin_min[col] = min(margin_min[col], margin)
                    stripe = float(1 << finest_bit[a])
                    for col in range(width):
                        inconsistent[col] |= stripe_index[col] * stripe >= axis_size[a]
                        reference[col] = stripe_index[col] * stripe + 0.5 * (stripe - 1.0)
                        axis_modulation[col] = margin_sum[col] / gray_count[a]
                        axis_quality[col] = margin_min[col] / axis_modulation[col] if axis_modulation[col] > 0 else 0.0
                    referenced = True
                    uncertainty = 0.5 * stripe
                for g in range(first_group, end_group):
                    period = group_period[g]
                    steps = group_start[g + 1] - group_start[g]
                    tolerance = uncertainty + consistency * (0.5 * period - uncertainty)
                    for col in range(width):
                        energy = c_sum[g, col] * c_sum[g, col] + s_sum[g, col] * s_sum[g, col]
                        alternating = squares[g, col] - total[g, col] * total[g, col] / steps
                        group_quality = min(1.0, 2.0 * energy / steps / alternating) if alternating > 0 else 0.0
                        axis_quality[col] = group_quality if g == first_group else min(axis_quality[col], group_quality)
                        axis_modulation[col] = 2.0 * math.sqrt(energy) / steps
                        phase = _polynomial_atan2(s_sum[g, col], c_sum[g, col])
                        wrapped = (phase / (2 * math.pi) + (1.0 if phase < 0 else 0.0)) * period
                        if referenced:
                            unwrapped = wrapped + period * math.floor((reference[col] - wrapped) / period + 0.5)
                            inconsistent[col] |= abs(unwrapped - reference[col]) > tolerance
                            reference[col] = unwrapped
                        else:
                            reference[col] = wrapped - period if wrapped > 0.5 * (axis_size[a] - 1 + period) else wrapped
                    referenced = True
                    uncertainty = 0.0
                phased = first_group < end_group
                for col in range(width):
                    poor_fit[col] |= phased and axis_quality[col] < min_quality
                    inconsistent[col] |= reference[col] < -0.5 or reference[col] > axis_size[a] - 0.5
                    coordinates[a, row, col] = reference[col]
                    pixel_modulation[col] = min(pixel_modulation[col], axis_modulation[col])
                    pixel_quality[col] = min(pixel_quality[col], axis_quality[col])

            for col in range(width):
                if level[col] < min_intensity:
                    reason = 1
                elif saturated[col]:
                    reason = 2
                elif pixel_modulation[col] < min_modulation:
                    reason = 3
                elif poor_fit[col]:
                    reason = 4
                elif inconsistent[col]:
                    reason = 5
                else:
                    reason = 0
                if reason != 0:
                    coordinates[0, row, col] = np.nan
                    coordinates[1, row, col] = np.nan
                modulation[row, col] = pixel_modulation[col]
                intensity[row, col] = level[col]
                quality[row, col] = pixel_quality[col]
                rejection[row, col] = reason


# Serial: a few passes over bytes cost about a millisecond, less than waking threads for them.
@njit(cache=True, fastmath=False)
def _edge_kernel(coordinates, rejection, margin, max_jump):
    """Mark valid pixels within ``margin`` pixels of a rejected one, or beside a jump above ``max_jump``."""
    height, width = rejection.shape
    near_row = np.zeros((height, width), np.bool_)  # a rejected pixel within margin along the row
    for row in range(height):
        for col in range(width):
            if rejection[row, col] != 0:
                near_row[row, max(0, col - margin):min(width, col + margin + 1)] = True
    jumps = np.isfinite(max_jump)
    for row in range(height):
        edge = np.zeros(width, np.bool_)
        for r in range(max(0, row - margin), min(height, row + margin + 1)):
            edge |= near_row[r]
        if jumps:
            for a in range(2):
                here = coordinates[a, row]
                for col in range(width - 1):
                    step = abs(here[col + 1] - here[col]) > max_jump
                    edge[col] |= step
                    edge[col + 1] |= step
                if row > 0:
                    edge |= np.abs(coordinates[a, row - 1] - here) > max_jump
                if row + 1 < height:
                    edge |= np.abs(coordinates[a, row + 1] - here) > max_jump
        for col in range(width):
            if edge[col] and rejection[row, col] == 0:
                rejection[row, col] = 6
    for row in range(height):  # after the jump test, which reads the neighbouring rows' coordinates
        for col in range(width):
            if rejection[row, col] == 6:
                coordinates[0, row, col] = np.nan
                coordinates[1, row, col] = np.nan


def _interpolate_gray_only_axes(frames: np.ndarray, sequence: Sequence, coordinates: np.ndarray,
                                rejection: np.ndarray) -> None:
    """Replace the stripe centres of Gray-code-only axes by ``gray_subpixel``'s coordinates, in place;
    pixels it cannot interpolate become ``INCONSISTENT``."""
    for a, axis in enumerate(AXES):
        if sequence.gray_planes(axis) and not sequence.phase_groups(axis):
            coordinates[a] = gray_subpixel(frames, sequence, axis, coordinates[a])
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
    consistency: float = 0.25,
    edge_margin: int = 3,
    max_jump: float = np.inf,
    gray_boundaries: bool = True,
    max_indirect: float = np.inf,
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
    tables = _sequence_tables(sequence)
    height, width = frames.shape[1:]
    coordinates = np.empty((2, height, width), np.float32)
    modulation = np.empty((height, width), np.float32)
    intensity = np.empty((height, width), np.float32)
    quality = np.empty((height, width), np.float32)
    rejection = np.empty((height, width), np.uint8)
    _decode_kernel(
        np.ascontiguousarray(frames), full_scale, tables.white, tables.black, tables.mean_frames, tables.axis_size,
        tables.gray_count, tables.gray_frame, tables.gray_complement, tables.gray_inverted, tables.finest_bit,
        tables.group_range, tables.group_start, tables.group_frames, tables.group_cos, tables.group_sin,
        tables.group_period, float(min_intensity), float(min_modulation), float(min_quality), float(consistency),
        min(height, 4 * get_num_threads()), coordinates, modulation, intensity, quality, rejection,
    )
    if np.isfinite(max_indirect) and sequence.phase_groups():
        _reject_indirect(coordinates, modulation, intensity, rejection, max_indirect)
    if edge_margin > 0 or np.isfinite(max_jump):
        _edge_kernel(coordinates, rejection, int(edge_margin), float(max_jump))
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
