"""Perceptual colour map for temperatures, so any PLY viewer (and the Rerun stream) shows the field."""

from __future__ import annotations

from functools import cache

import numpy as np

DEFAULT_COLORMAP = "inferno"
UNSEEN_COLOR = (128, 128, 128)


@cache
def colormap_lut(name: str = DEFAULT_COLORMAP) -> np.ndarray:
    """(256, 3) uint8 RGB lookup table of a matplotlib colour map, computed once per name."""
    from matplotlib import colormaps  # imported lazily: matplotlib is slow to import

    if name not in colormaps:
        raise ValueError(f"Unknown colour map {name!r}; use a matplotlib name such as 'inferno' or 'turbo'.")
    lut = colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3]
    lut = np.round(lut * 255).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def temperature_colors(
    temperature: np.ndarray,
    vmin: float | None = None,
    vmax: float | None = None,
    name: str = DEFAULT_COLORMAP,
) -> np.ndarray:
    """RGB colours of temperatures on a perceptual colour map.

    Parameters
    ----------
    temperature : (N,) array
        Temperatures; NaN for unseen points.
    vmin, vmax : float, optional
        Temperatures at the ends of the map; default the finite minimum and
        maximum.
    name : str
        A matplotlib colour map; perceptually uniform ones (``inferno``,
        ``magma``, ``viridis``) keep equal temperature steps equally visible [1]_.

    Returns
    -------
    rgb : (N, 3) uint8 array
        Colours; unseen points are mid grey.

    References
    ----------
    .. [1] N. Smith and S. van der Walt, "A Better Default Colormap for
       Matplotlib", SciPy 2015.
    """
    temperature = np.asarray(temperature, dtype=np.float64)
    finite = np.isfinite(temperature)
    rgb = np.empty(temperature.shape + (3,), dtype=np.uint8)
    rgb[...] = UNSEEN_COLOR
    if not finite.any():
        return rgb
    low = np.min(temperature[finite]) if vmin is None else vmin
    high = np.max(temperature[finite]) if vmax is None else vmax
    if not high > low:
        high = low + 1.0
    scaled = np.clip((temperature[finite] - low) / (high - low), 0.0, 1.0)
    rgb[finite] = colormap_lut(name)[np.round(scaled * 255).astype(np.intp)]
    return rgb
