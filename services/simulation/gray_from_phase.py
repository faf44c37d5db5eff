"""A Gray-code-only capture of a real scene, rendered from what its real phase-shift capture measures.

A real phase-shift capture gives at every camera pixel the offset A, the modulation B and the projector
coordinate c of the surface the pixel sees, and, from two phase groups that both estimate A, the camera
noise. A Gray-code capture of the same scene is then A + B (2 g(c) - 1) per plane, with the binary edges
blurred by the camera's blur and that noise added: the real geometry, albedo, shading, inter-reflections'
loss of modulation and outline, with the Gray planes' own edges. Used to measure Gray-only decoding on
SLStudio's real skull, for which no Gray-code capture is shared (docs/real-data.md).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

from services.formats.sequence import Sequence
from services.structured_light.decode import Rejection, decode
from services.structured_light.outline import ASSUMED_CAMERA_BLUR_PX, estimate_camera_blur


def gray_frames_from_phase(frames: np.ndarray, sequence: Sequence, gray_sequence: Sequence,
                           rng: np.random.Generator, *, consistency: float = 0.5) -> tuple[np.ndarray, float, float]:
    """Frames of ``gray_sequence`` (white, black, column Gray planes) from a real two-period phase capture.

    Parameters
    ----------
    frames : (F, H, W) uint8 array
        The real capture: column phase shifting at two or more periods (the finest first in the
        manifest's order of groups does not matter).
    sequence : Sequence
        Its manifest.
    gray_sequence : Sequence
        White, black and column Gray planes (with or without inverses) for the same projector.
    rng : numpy.random.Generator
        Source of the added noise.
    consistency : float
        ``decode``'s tolerance for unwrapping the real capture.

    Returns
    -------
    frames : (F', H, W) uint8 array
        One frame per ``gray_sequence`` frame.
    noise : float
        The camera noise added, grey levels.
    blur : float
        The camera blur the Gray planes' edges were blurred by, pixels.

    Notes
    -----
    A = the mean of the finest group's frames, B its modulation and c the unwrapped column (``decode``),
    filled from the nearest decoded pixel where it was not decoded (dark, inconsistent pixels keep their
    own A and B). A plane showing Gray bit b reads A + B blur(2 g_b(c) - 1), its inverse the negation,
    white A + B and black A - B, g_b(c) = bit b of the Gray code of the projector pixel round(c). The
    camera blur s is ``estimate_camera_blur``'s on the real capture. The noise sigma is measured from the
    capture: the means of two phase groups both estimate A, their difference has variance
    sigma^2 (1 / N_1 + 1 / N_2) over the pixels that are not dark.
    """
    frames = np.asarray(frames)
    if frames.ndim != 3 or frames.dtype != np.uint8:
        raise ValueError(f"The real capture must be a (F, H, W) uint8 stack; got {frames.shape} {frames.dtype}.")
    groups = sequence.phase_groups("x")
    if len(groups) < 2:
        raise ValueError("The real capture needs two column phase groups: one to decode, one more to measure "
                         "the noise by.")
    if gray_sequence.projector != sequence.projector:
        raise ValueError("The Gray sequence is for another projector than the real capture.")
    finest = min(groups, key=lambda group: group.period)
    other = next(group for group in groups if group is not finest)
    real = frames.astype(np.float64)
    offset = real[list(finest.frames)].mean(axis=0)
    decoded = decode(frames, sequence, consistency=consistency, edge_margin=0)
    coordinate = decoded.projector_x.astype(np.float64)
    known = np.isfinite(coordinate)
    if not known.any():
        raise ValueError("No pixel of the real capture decodes, so there is no scene to render.")
    nearest = distance_transform_edt(~known, return_distances=False, return_indices=True)
    coordinate = coordinate[nearest[0], nearest[1]]
    not_dark = decoded.rejection != Rejection.DARK
    difference = offset - real[list(other.frames)].mean(axis=0)
    noise = float(np.std(difference[not_dark]) / np.sqrt(1 / len(finest.frames) + 1 / len(other.frames)))
    blur = estimate_camera_blur(decoded.intensity, decoded.rejection) or ASSUMED_CAMERA_BLUR_PX
    column = np.clip(np.rint(coordinate), 0, sequence.projector.width - 1).astype(np.int64)
    gray = column ^ (column >> 1)
    modulation = decoded.modulation.astype(np.float64)
    out = np.empty((len(gray_sequence.frames),) + frames.shape[1:], np.uint8)
    for index, frame in enumerate(gray_sequence.frames):
        if frame.kind == "white":
            sign = np.ones_like(coordinate)
        elif frame.kind == "black":
            sign = -np.ones_like(coordinate)
        elif frame.kind == "gray" and frame.axis == "x":
            sign = cv2.GaussianBlur(2.0 * ((gray >> frame.bit) & 1) - 1.0, (0, 0), blur)
            if frame.inverted:
                sign = -sign
        else:
            raise ValueError(f"Frame {index} of the Gray sequence is a {frame.kind} frame; only white, black "
                             "and column Gray planes can be rendered from a column phase capture.")
        image = offset + modulation * sign + rng.normal(0.0, noise, coordinate.shape)
        out[index] = np.clip(np.rint(image), 0, 255).astype(np.uint8)
    return out, noise, float(blur)
