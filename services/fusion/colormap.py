"""Perceptual colour map for temperatures, so any PLY viewer (and the Rerun stream) shows the field.

The lookup tables come from OpenCV's colour maps (equal, entry for entry, to matplotlib's for the names in
``OPENCV_COLORMAPS``) and from Moreland's published cool-warm table; matplotlib, slow to import, is imported
only for other names.
"""

from __future__ import annotations

from functools import cache

import cv2
import numpy as np

from services.structured_light.row_bands import map_bands, row_bands

DEFAULT_COLORMAP = "inferno"
UNSEEN_COLOR = (128, 128, 128)
CHUNK = 1 << 16
"""Temperatures per chunk of the colouring (on the row-band pool)."""

OPENCV_COLORMAPS = {
    "inferno": cv2.COLORMAP_INFERNO,
    "magma": cv2.COLORMAP_MAGMA,
    "plasma": cv2.COLORMAP_PLASMA,
    "viridis": cv2.COLORMAP_VIRIDIS,
    "cividis": cv2.COLORMAP_CIVIDIS,
    "turbo": cv2.COLORMAP_TURBO,
}
"""Colour maps whose OpenCV tables equal matplotlib's 256-entry ones (OpenCV's jet, hot, twilight, ...
differ from matplotlib's of the same name, so those names go to matplotlib)."""

# Moreland's cool-warm diverging map [1], his 33-sample table (CoolWarmFloat33) of sRGB in [0, 1] at
# 0, 1/32, ..., 1, interpolated linearly, as matplotlib's "coolwarm".
_COOLWARM_33 = np.array([
    (0.2298057, 0.298717966, 0.753683153),
    (0.26623388, 0.353094838, 0.801466763),
    (0.30386891, 0.406535296, 0.84495867),
    (0.342804478, 0.458757618, 0.883725899),
    (0.38301334, 0.50941904, 0.917387822),
    (0.424369608, 0.558148092, 0.945619588),
    (0.46666708, 0.604562568, 0.968154911),
    (0.509635204, 0.648280772, 0.98478814),
    (0.552953156, 0.688929332, 0.995375608),
    (0.596262162, 0.726149107, 0.999836203),
    (0.639176211, 0.759599947, 0.998151185),
    (0.681291281, 0.788964712, 0.990363227),
    (0.722193294, 0.813952739, 0.976574709),
    (0.761464949, 0.834302879, 0.956945269),
    (0.798691636, 0.849786142, 0.931688648),
    (0.833466556, 0.860207984, 0.901068838),
    (0.865395197, 0.86541021, 0.865395561),
    (0.897787179, 0.848937047, 0.820880546),
    (0.924127593, 0.827384882, 0.774508472),
    (0.944468518, 0.800927443, 0.726736146),
    (0.958852946, 0.769767752, 0.678007945),
    (0.96732803, 0.734132809, 0.628751763),
    (0.969954137, 0.694266682, 0.579375448),
    (0.966811177, 0.650421156, 0.530263762),
    (0.958003065, 0.602842431, 0.481775914),
    (0.943660866, 0.551750968, 0.434243684),
    (0.923944917, 0.49730856, 0.387970225),
    (0.89904617, 0.439559467, 0.343229596),
    (0.869186849, 0.378313092, 0.300267182),
    (0.834620542, 0.312874446, 0.259301199),
    (0.795631745, 0.24128379, 0.220525627),
    (0.752534934, 0.157246067, 0.184115123),
    (0.705673158, 0.01555616, 0.150232812),
])


@cache
def colormap_lut(name: str = DEFAULT_COLORMAP) -> np.ndarray:
    """(256, 3) uint8 RGB lookup table of a colour map, computed once per name.

    Parameters
    ----------
    name : str
        One of ``OPENCV_COLORMAPS``, ``"coolwarm"``, or (when matplotlib is
        installed) any matplotlib colour map.

    Returns
    -------
    lut : (256, 3) uint8 array, read-only
        Entry i is the map's colour at i / 255, as matplotlib's
        ``round(255 * colormaps[name](i / 255))``.

    Notes
    -----
    OpenCV's ``applyColorMap`` on the ramp 0..255 gives the BGR table of its
    maps. The cool-warm map interpolates Moreland's table linearly in sRGB [1]_.

    References
    ----------
    .. [1] K. Moreland, "Diverging Color Maps for Scientific Visualization",
       Advances in Visual Computing (ISVC 2009), LNCS 5876, pp. 92-103; the
       table CoolWarmFloat33 of https://www.kennethmoreland.com/color-maps/.
    """
    if name in OPENCV_COLORMAPS:
        ramp = np.arange(256, dtype=np.uint8)[:, None]
        lut = np.ascontiguousarray(cv2.applyColorMap(ramp, OPENCV_COLORMAPS[name])[:, 0, ::-1])
    elif name == "coolwarm":
        samples = np.linspace(0.0, 1.0, len(_COOLWARM_33))
        ramp = np.linspace(0.0, 1.0, 256)
        rgb = np.column_stack([np.interp(ramp, samples, _COOLWARM_33[:, channel]) for channel in range(3)])
        lut = np.round(rgb * 255).astype(np.uint8)
    else:
        lut = _matplotlib_lut(name)
    lut.flags.writeable = False
    return lut


def _matplotlib_lut(name: str) -> np.ndarray:
    known = ", ".join(repr(known) for known in (*OPENCV_COLORMAPS, "coolwarm"))
    try:
        from matplotlib import colormaps  # imported lazily: matplotlib is slow to import
    except ImportError:
        raise ValueError(f"Unknown colour map {name!r}; use one of {known}.") from None
    if name not in colormaps:
        raise ValueError(f"Unknown colour map {name!r}; use one of {known} or another matplotlib name.")
    return np.round(colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255).astype(np.uint8)


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
        A colour map (see :func:`colormap_lut`); perceptually uniform ones (``inferno``,
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
    temperature = np.asarray(temperature)
    if temperature.dtype not in (np.float32, np.float64):
        temperature = temperature.astype(np.float64)
    rgb = np.empty(temperature.shape + (3,), dtype=np.uint8)
    low, high = vmin, vmax
    if low is None or high is None:
        finite = temperature[np.isfinite(temperature)] if temperature.size else temperature
        if not finite.size:
            rgb[...] = UNSEEN_COLOR
            return rgb
        low = float(np.min(finite)) if low is None else low
        high = float(np.max(finite)) if high is None else high
    if not high > low:
        high = low + 1.0
    lut = colormap_lut(name)
    flat, colours = temperature.reshape(-1), rgb.reshape(-1, 3)

    def chunk(rows: slice) -> None:
        values = np.asarray(flat[rows], dtype=np.float64)
        finite = np.isfinite(values)
        values -= low
        values /= high - low
        np.clip(values, 0.0, 1.0, out=values)
        values *= 255
        np.round(values, out=values)
        values[~finite] = 0.0
        chunk_colours = lut[values.astype(np.intp)]
        chunk_colours[~finite] = UNSEEN_COLOR
        colours[rows] = chunk_colours

    map_bands(chunk, row_bands(len(flat), 1, CHUNK))
    return rgb
