"""Windowed decoding of weak fringes: the phase from demodulated quadrature sums over a small window.

Where a glowing part's shot noise buries the fringes of one pixel, its neighbours on the same surface
carry the same fringes at a phase that changes linearly across a few pixels. Summing their quadrature
sums, demodulated by that local fringe frequency, measures the centre's phase with the noise of the
whole window (Kemao's windowed Fourier filtering, with one frequency per pixel instead of a search).
"""

from __future__ import annotations

import cv2
import numpy as np

from services.formats.sequence import Sequence

_MIN_COVERAGE = 0.9  # share of the window's weight that must lie on the supporting pixels


def _window(sigma_px: float) -> tuple[np.ndarray, int]:
    radius = max(1, int(np.ceil(2 * sigma_px)))
    offsets = np.arange(-radius, radius + 1)
    weights = np.exp(-0.5 * (offsets[:, None] ** 2 + offsets[None, :] ** 2) / sigma_px**2)
    return weights / weights.sum(), radius


def _shifted(image: np.ndarray, dy: int, dx: int, radius: int) -> np.ndarray:
    """image[r + dy, c + dx] for every (r, c) of the unpadded image, from an image padded by ``radius``."""
    height, width = image.shape[0] - 2 * radius, image.shape[1] - 2 * radius
    return image[radius + dy:radius + dy + height, radius + dx:radius + dx + width]


def windowed_frames(
    frames: np.ndarray,
    sequence: Sequence,
    support: np.ndarray,
    *,
    sigma_px: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frames of a sequence averaged over a Gaussian window on the supporting pixels, fringes demodulated.

    Parameters
    ----------
    frames : (F, H, W) float32 array
        Offset-free grey levels (the glow removed), one frame per manifest frame.
    sequence : Sequence
        What each frame encodes; its phase groups are demodulated.
    support : (H, W) bool array
        The pixels that may contribute (one surface: the glowing part, the rejected ones left out).
    sigma_px : float
        Standard deviation of the Gaussian window, camera pixels (the window spans +- 2 sigma).

    Returns
    -------
    windowed : (F, H, W) float32 array
        Gray-code and reference frames: their normalised windowed mean. Phase frames: the sinusoid
        whose quadrature sums are the window's demodulated sums, so that ``decode`` reads the
        windowed phase. NaN where less than 90 % of the window's weight lies on the support.
    noise_gain : (H, W) float32 array
        Standard deviation of the windowed mean of white noise of unit variance on the support; NaN
        where less than 90 % of the window's weight lies on the support (a window across an outline).
    coverage : (H, W) float32 array
        Share of the window's weight on the support.

    Notes
    -----
    With the window weights w_j on the supporting neighbours j of pixel 0 (normalised convolution [1]_),
    a frame's windowed value is sum_j w_j I_j / sum_j w_j, of noise sigma sqrt(sum_j w_j^2) / sum_j w_j.
    For each phase group, z_j = sum_k I_jk exp(i 2 pi k / N) = (N B_j / 2) exp(i phi_j). The local
    fringe frequency g (radians per pixel, per image axis) is the phase step between the windowed z
    of the two neighbours, g_x = arg(Z_(x+1) conj(Z_(x-1))) / 2, and the windowed sum is demodulated
    by it [2]_:

        Z_0 = sum_j w_j z_j exp(-i g . d_j) / sum_j w_j

    with d_j the offset of neighbour j. For a phase linear across the window, phi_j = phi_0 + g . d_j,
    Z_0 = exp(i phi_0) sum_j w_j N B_j / 2 / sum_j w_j: the centre's phase whatever the modulation
    does across the window (a terminator, where it ramps to zero), where an undemodulated sum would
    read the phase at the modulation-weighted centroid. The phase frames returned are
    I_k = A + (2 / N) Re(Z_0 exp(-i 2 pi k / N)), A the windowed mean level.

    Gray-code planes are averaged without demodulation: a window across a plane's transition may misread
    that one bit near the transition, where the stripe index is then off by one stripe, which
    complementary unwrapping tolerates (the stripe centre stays within a quarter period of the truth).

    References
    ----------
    .. [1] H. Knutsson, C.-F. Westin, "Normalized and differential convolution", CVPR 1993, 515-523.
    .. [2] Q. Kemao, "Windowed Fourier transform for fringe pattern analysis", Applied Optics 43(13),
       2695-2702, 2004; "Two-dimensional windowed Fourier transform for fringe pattern analysis:
       principles, applications and implementations", Optics and Lasers in Engineering 45(2), 304-317, 2007.
    """
    frames = np.asarray(frames, dtype=np.float32)
    support = np.asarray(support, dtype=bool)
    if frames.ndim != 3 or support.shape != frames.shape[1:]:
        raise ValueError(f"frames must be (F, H, W) and support (H, W); got {frames.shape} and {support.shape}.")
    if len(frames) != len(sequence.frames):
        raise ValueError(f"The sequence has {len(sequence.frames)} frames but {len(frames)} were given.")
    if not sigma_px > 0:
        raise ValueError(f"The window's sigma must be a positive number of pixels; got {sigma_px}.")
    weights, radius = _window(sigma_px)
    mask = support.astype(np.float32)
    kernel = weights.astype(np.float32)
    weight_sum = cv2.filter2D(mask, -1, kernel, borderType=cv2.BORDER_CONSTANT)
    square_sum = cv2.filter2D(mask, -1, kernel * kernel, borderType=cv2.BORDER_CONSTANT)
    with np.errstate(divide="ignore", invalid="ignore"):
        noise_gain = np.sqrt(square_sum) / weight_sum
    coverage = weight_sum  # the kernel sums to 1
    noise_gain[~(coverage >= _MIN_COVERAGE)] = np.nan

    def normalised(image: np.ndarray) -> np.ndarray:
        summed = cv2.filter2D(np.where(support, image, 0).astype(np.float32), -1, kernel,
                              borderType=cv2.BORDER_CONSTANT)
        with np.errstate(divide="ignore", invalid="ignore"):
            return summed / weight_sum

    windowed = np.stack([normalised(frame) for frame in frames])
    for group in sequence.phase_groups():
        steps = len(group.frames)
        shifts = np.exp(1j * 2 * np.pi * np.arange(steps) / steps).astype(np.complex64)
        z = np.tensordot(shifts, frames[list(group.frames)], axes=1)  # C + i S per pixel
        z = np.where(support, z, 0)
        smoothed = normalised(z.real) + 1j * normalised(z.imag)
        smoothed = np.nan_to_num(smoothed)
        g_x = np.zeros(z.shape, np.float32)
        g_y = np.zeros(z.shape, np.float32)
        g_x[:, 1:-1] = np.angle(smoothed[:, 2:] * np.conj(smoothed[:, :-2])) / 2
        g_y[1:-1, :] = np.angle(smoothed[2:, :] * np.conj(smoothed[:-2, :])) / 2
        padded = np.pad(z, radius)
        total = np.zeros(z.shape, np.complex64)
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                phase = -(g_x * dx + g_y * dy)
                total += weights[dy + radius, dx + radius] * _shifted(padded, dy, dx, radius) * (
                    np.cos(phase) + 1j * np.sin(phase))
        with np.errstate(divide="ignore", invalid="ignore"):
            demodulated = total / weight_sum
        mean_level = np.mean(windowed[list(group.frames)], axis=0)
        for k, index in enumerate(group.frames):
            windowed[index] = mean_level + (2 / steps) * np.real(demodulated * np.conj(shifts[k]))
    windowed[:, ~np.isfinite(noise_gain)] = np.nan
    return windowed, noise_gain.astype(np.float32), coverage.astype(np.float32)
