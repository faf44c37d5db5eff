"""Projector patterns: the default coded sequence, and the images of any sequence manifest.

The default sequence (see docs/coding.md for the measurements behind it) is a
white and a black reference, then per coded axis a complementary Gray code
(every bit plane followed by its inverse, one bit finer than the phase period
needs) and an N-step phase-shifted sinusoid unwrapped by that Gray code.
"""

from __future__ import annotations

import math

import numpy as np

from services.formats.sequence import BlackFrame, GrayFrame, PhaseFrame, ProjectorSize, Sequence, WhiteFrame

DEFAULT_PERIOD = 16
DEFAULT_STEPS = 12


def complementary_gray_bit(period: float) -> int:
    """The finest Gray bit of complementary unwrapping: stripes at most half a period wide.

    Notes
    -----
    Stripes are ``2**bit`` pixels wide; the largest bit with ``2**bit <= period / 2``
    (at least 0) lets the phase be unwrapped against the stripe centre with a
    margin of at least a quarter period [1]_.

    References
    ----------
    .. [1] Q. Zhang, X. Su, L. Xiang, X. Sun, "3-D shape measurement based on
       complementary Gray-code light", Optics and Lasers in Engineering 50(4), 574-579 (2012).
    """
    if period < 1:
        raise ValueError(f"The phase period must be at least 1 projector pixel; got {period}.")
    return max(0, int(math.floor(math.log2(period / 2))))


def generate_sequence(
    width: int,
    height: int,
    *,
    axes: str = "x",
    period: float = DEFAULT_PERIOD,
    steps: int = DEFAULT_STEPS,
    closing_black: bool = False,
) -> tuple[Sequence, np.ndarray]:
    """The default structured-light sequence for a projector, and its images.

    Parameters
    ----------
    width, height : int
        Projector size in pixels.
    axes : {"x", "y", "xy"}
        Projector axes to code: columns (x), rows (y) or both.
    period : float
        Phase-shift period in projector pixels.
    steps : int
        Number of phase shifts N (at least 3).
    closing_black : bool
        End with a second black frame, so that a hot part's glow, which drifts as the part cools, can
        be interpolated between the opening and the closing black frame and subtracted (see
        docs/hot-parts.md).

    Returns
    -------
    sequence : Sequence
        The manifest: white, black, then per axis the Gray planes most significant
        first, each followed by its inverse, then the N phase steps (and the closing black frame).
    patterns : (F, height, width) uint8 array
        The projector images in display order.

    Notes
    -----
    Frames per axis: ``2 (ceil(log2 size) - b) + N`` with ``b`` from
    :func:`complementary_gray_bit`; for 1280 columns, period 16 and N = 12 that is
    2 + 16 + 12 = 30 frames.
    """
    if axes not in ("x", "y", "xy"):
        raise ValueError(f"axes must be 'x', 'y' or 'xy'; got {axes!r}.")
    if steps < 3:
        raise ValueError(f"Phase shifting needs at least 3 steps; got {steps}.")
    if width < 1 or height < 1:
        raise ValueError(f"The projector size must be positive; got {width}x{height}.")
    finest_bit = complementary_gray_bit(period)
    frames: list = [WhiteFrame(kind="white", file="00_white.png"), BlackFrame(kind="black", file="01_black.png")]
    for axis in axes:
        size = width if axis == "x" else height
        top_bit = max(1, (size - 1).bit_length()) - 1
        for bit in range(top_bit, min(finest_bit, top_bit) - 1, -1):
            for inverted in (False, True):
                suffix = "_inv" if inverted else ""
                frames.append(GrayFrame(kind="gray", file=f"{len(frames):02d}_gray_{axis}_bit{bit:02d}{suffix}.png",
                                        axis=axis, bit=bit, inverted=inverted))
        for step in range(steps):
            frames.append(PhaseFrame(kind="phase", file=f"{len(frames):02d}_phase_{axis}_step{step}.png",
                                     axis=axis, period=period, step=step, steps=steps))
    if closing_black:
        frames.append(BlackFrame(kind="black", file=f"{len(frames):02d}_black_closing.png"))
    sequence = Sequence(projector=ProjectorSize(width=width, height=height), frames=frames)
    return sequence, render_patterns(sequence)


def _gray_profile(size: int, bit: int, inverted: bool) -> np.ndarray:
    coordinate = np.arange(size)
    lit = ((coordinate ^ (coordinate >> 1)) >> bit) & 1
    return (lit ^ int(inverted)).astype(np.uint8) * 255


def _phase_profile(size: int, period: float, step: int, steps: int) -> np.ndarray:
    coordinate = np.arange(size, dtype=np.float64)
    level = 0.5 + 0.5 * np.cos(2 * np.pi * coordinate / period - 2 * np.pi * step / steps)
    return np.rint(255 * level).astype(np.uint8)


def render_patterns(sequence: Sequence) -> np.ndarray:
    """The 8-bit projector image of every frame of a manifest, in display order.

    Parameters
    ----------
    sequence : Sequence

    Returns
    -------
    patterns : (F, height, width) uint8 array

    Notes
    -----
    With ``c`` the projector coordinate along the frame's axis (pixel centres at
    integers), a Gray frame is 255 where bit ``bit`` of ``c XOR (c >> 1)`` is 1
    (0 when inverted), and a phase frame is
    ``round(255 (1/2 + 1/2 cos(2 pi c / period - 2 pi step / steps)))``.
    """
    width, height = sequence.projector.width, sequence.projector.height
    patterns = np.empty((len(sequence.frames), height, width), dtype=np.uint8)
    for index, frame in enumerate(sequence.frames):
        if frame.kind in ("white", "black"):
            patterns[index] = 255 if frame.kind == "white" else 0
            continue
        size = sequence.axis_size(frame.axis)
        if frame.kind == "gray":
            profile = _gray_profile(size, frame.bit, frame.inverted)
        else:
            profile = _phase_profile(size, frame.period, frame.step, frame.steps)
        patterns[index] = profile[None, :] if frame.axis == "x" else profile[:, None]
    return patterns

