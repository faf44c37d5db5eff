"""High dynamic range captures: one sequence filmed at several exposures, merged per pixel."""

from __future__ import annotations

import numpy as np

_UINT16_MAX = 65535


def merge_exposures(stacks: np.ndarray, exposures_us: list[float], saturation_level: float) -> tuple[np.ndarray, int]:
    """Merge captures of one sequence at several exposures (repeats allowed) into one stack of wider range.

    Parameters
    ----------
    stacks : (E, F, H, W) uint8 or uint16 array
        The sequence's frames at each of E exposures; an exposure time may occur more than once (the
        sequence filmed again at it, to collect more photons where every longer exposure saturates).
    exposures_us : list of float
        The E exposure times.
    saturation_level : float
        Grey level at which the sensor saturates.

    Returns
    -------
    merged : (F, H, W) uint16 array
        Per pixel, the exposure-weighted mean of every exposure in which none of its frames saturates,
        in units of the longest exposure; pixels saturated at every exposure read the merged saturation
        level.
    merged_saturation : int
        The merged stack's saturation level.

    Notes
    -----
    A pixel of photon rate r filmed for t_e reads I_e = g r t_e plus noise, shot-noise limited on a
    glowing part (variance g I_e; the 2.5 e- read noise is negligible beside it). Over the set U of the
    exposures in which none of the pixel's frames saturates, the maximum-likelihood estimate of r from
    independent Poisson counts is sum_U I_e / sum_U t_e, the weighting w_e proportional to t_e of the
    noise-optimal merges [1]_ [2]_, whose variance g r / sum_U t_e falls with the total time collected:
    K repeats of one exposure give sqrt(K) times the signal-to-noise ratio of one. The merge reads

        I = s t_max sum_U I_e / sum_U t_e

    with t_max the longest exposure and s <= 1 keeping saturation (t_max / t_min) s within 16 bits [3]_.
    One set U for all the frames of a pixel keeps its phase samples consistent, and the weights do not
    change from frame to frame, so a glow that drifts linearly over each repeat drifts linearly over
    the merge.

    References
    ----------
    .. [1] M. Granados, B. Ajdin, M. Wand, C. Theobalt, H.-P. Seidel, H. P. A. Lensch, "Optimal HDR
       reconstruction with linear digital cameras", CVPR 2010, 215-222.
    .. [2] M. A. Robertson, S. Borman, R. L. Stevenson, "Estimation-theoretic approach to dynamic range
       enhancement using multiple exposures", Journal of Electronic Imaging 12(2), 219-228, 2003.
    .. [3] S. Zhang and S.-T. Yau, "High dynamic range scanning technique", Optical Engineering 48(3),
       033604, 2009.
    """
    stacks = np.asarray(stacks)
    exposures = np.asarray(exposures_us, dtype=np.float64)
    if stacks.ndim != 4 or len(stacks) != len(exposures) or len(exposures) < 1:
        raise ValueError(f"stacks must be (E, F, H, W) with one exposure time each; got {stacks.shape} and "
                         f"{len(exposures)} exposures.")
    if np.any(exposures <= 0):
        raise ValueError(f"Exposure times must be positive; got {exposures_us}.")
    longest, shortest = float(exposures.max()), float(exposures.min())
    scale = min(1.0, _UINT16_MAX / (saturation_level * longest / shortest))
    merged_saturation = int(np.floor(saturation_level * longest / shortest * scale))
    total = np.zeros(stacks.shape[1:], dtype=np.float64)
    time_collected = np.zeros(stacks.shape[2:], dtype=np.float64)
    for stack, exposure in zip(stacks, exposures):
        usable = ~np.any(stack >= saturation_level, axis=0)
        total[:, usable] += stack[:, usable]
        time_collected[usable] += exposure
    merged = np.full(stacks.shape[1:], merged_saturation, dtype=np.uint16)
    measured = time_collected > 0
    rate = total[:, measured] / time_collected[measured]
    merged[:, measured] = np.minimum(np.rint(rate * (longest * scale)), merged_saturation - 1)
    return merged, merged_saturation
