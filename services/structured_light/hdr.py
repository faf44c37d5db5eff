"""High dynamic range captures: one sequence filmed at several exposures, merged per pixel."""

from __future__ import annotations

import numpy as np

_UINT16_MAX = 65535


def merge_exposures(stacks: np.ndarray, exposures_us: list[float], saturation_level: float) -> tuple[np.ndarray, int]:
    """Merge captures of one sequence at several exposures into one stack of wider range.

    Parameters
    ----------
    stacks : (E, F, H, W) uint8 or uint16 array
        The sequence's frames at each of E exposures.
    exposures_us : list of float
        The E exposure times.
    saturation_level : float
        Grey level at which the sensor saturates.

    Returns
    -------
    merged : (F, H, W) uint16 array
        Per pixel, the frames of the longest exposure in which none of them saturates, scaled to a
        common unit; pixels saturated at every exposure read the merged saturation level.
    merged_saturation : int
        The merged stack's saturation level.

    Notes
    -----
    With t_e the exposures and t_max the longest, a pixel taken from exposure e reads
    I = I_e (t_max / t_e) s, where s <= 1 keeps (saturation (t_max / t_min) s) within 16 bits [1]_. Taking
    one exposure for all the frames of a pixel keeps its phase samples consistent; the longest
    unsaturated one has the best signal-to-noise ratio.

    References
    ----------
    .. [1] S. Zhang and S.-T. Yau, "High dynamic range scanning technique", Optical Engineering 48(3),
       033604, 2009.
    """
    stacks = np.asarray(stacks)
    exposures = np.asarray(exposures_us, dtype=np.float64)
    if stacks.ndim != 4 or len(stacks) != len(exposures) or len(exposures) < 1:
        raise ValueError(f"stacks must be (E, F, H, W) with one exposure time each; got {stacks.shape} and "
                         f"{len(exposures)} exposures.")
    if np.any(exposures <= 0):
        raise ValueError(f"Exposure times must be positive; got {exposures_us}.")
    order = np.argsort(exposures)
    stacks, exposures = stacks[order], exposures[order]
    ratio = exposures[-1] / exposures
    scale = min(1.0, _UINT16_MAX / (saturation_level * ratio[0]))
    merged_saturation = int(np.floor(saturation_level * ratio[0] * scale))
    saturated = np.stack([np.any(stack >= saturation_level, axis=0) for stack in stacks])  # (E, H, W)
    merged = np.full(stacks.shape[1:], merged_saturation, dtype=np.uint16)
    chosen = np.zeros(stacks.shape[2:], dtype=bool)
    for e in range(len(stacks) - 1, -1, -1):  # longest first
        take = ~saturated[e] & ~chosen
        merged[:, take] = np.minimum(np.rint(stacks[e][:, take] * (ratio[e] * scale)), merged_saturation - 1)
        chosen |= take
    return merged, merged_saturation
