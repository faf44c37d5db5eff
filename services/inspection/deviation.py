"""Surface deviation: signed distances of cold-equivalent points from the nominal surface, summary and defects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from services.inspection.nominal import NominalSurface


@dataclass(frozen=True)
class DeviationSummary:
    """Statistics of the signed deviations (mm) of the part's points."""

    points: int
    mean: float
    std: float
    min: float
    max: float
    fraction_outside: float


@dataclass(frozen=True)
class Defect:
    """A dent (depth < 0) or bulge (> 0): a connected patch of the deviation map beyond the threshold."""

    center: np.ndarray  # part frame, mm
    depth_mm: float
    area_mm2: float
    points: int


def surface_deviation(points_part: np.ndarray, nominal: NominalSurface) -> np.ndarray:
    """Signed distance (mm) of each point (part frame) from the nominal surface; positive is excess material.

    See :meth:`NominalSurface.closest` for how the sign is found.
    """
    return nominal.closest(points_part).signed_distance


def summarize_deviation(deviation: np.ndarray, tolerance: tuple[float, float]) -> DeviationSummary:
    """Mean, standard deviation, extremes and the fraction outside ``tolerance`` of the finite deviations."""
    finite = deviation[np.isfinite(deviation)]
    if len(finite) == 0:
        nan = float("nan")
        return DeviationSummary(0, nan, nan, nan, nan, nan)
    outside = (finite < tolerance[0]) | (finite > tolerance[1])
    return DeviationSummary(points=len(finite), mean=float(finite.mean()), std=float(finite.std()),
                            min=float(finite.min()), max=float(finite.max()), fraction_outside=float(outside.mean()))


def find_defects(points_part: np.ndarray, deviation: np.ndarray, threshold_mm: float, cell_mm: float = 1.0,
                 min_cells: int = 10) -> list[Defect]:
    """Dents and bulges: connected patches where the locally averaged deviation passes +- ``threshold_mm``.

    Parameters
    ----------
    points_part : (N, 3) array
        Points in the part frame.
    deviation : (N,) array
        Their signed deviations (NaN for points that are not the part's).
    threshold_mm : float
        A patch is a dent where the mean deviation of its cells is below -threshold, a bulge above.
    cell_mm : float
        Edge of the cubic cells the deviation is averaged over (smooths the structured-light noise).
    min_cells : int
        Smaller patches are noise or the ragged edge of the view (10 cells of 1 mm: 10 mm^2).

    Returns
    -------
    list of Defect
        Deepest first.

    Notes
    -----
    The points are binned into cubic cells of edge ``cell_mm``; each cell's deviation is the mean
    of its points'. Cells beyond the threshold are grouped by 26-connectivity after a one-cell
    dilation (``scipy.ndimage``), so that the gaps of a cloud sparser than the cells do not split a
    patch. A patch's depth is the extreme cell mean, its centre that cell's
    point centroid, its area the cell count times cell_mm^2.
    """
    finite = np.isfinite(deviation) & np.isfinite(points_part).all(axis=1)
    if finite.sum() == 0:
        return []
    points, values = points_part[finite], deviation[finite]
    cells = np.floor(points / cell_mm).astype(np.int64)
    low = cells.min(axis=0)
    cells -= low
    shape = cells.max(axis=0) + 1
    flat = np.ravel_multi_index(cells.T, shape)
    keys, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    mean = np.bincount(inverse, weights=values) / counts
    centroid = np.column_stack([np.bincount(inverse, weights=points[:, k]) / counts for k in range(3)])
    defects = []
    for sign in (-1.0, 1.0):
        beyond = sign * mean > threshold_mm
        if not beyond.any():
            continue
        grid = np.zeros(np.prod(shape), dtype=bool)
        grid[keys[beyond]] = True
        # cells one empty cell apart belong together: a cloud sparser than the cells leaves such gaps
        bridged = ndimage.binary_dilation(grid.reshape(shape), structure=np.ones((3, 3, 3)))
        labels, _ = ndimage.label(bridged, structure=np.ones((3, 3, 3)))
        cell_labels = labels.ravel()[keys[beyond]]
        beyond_index = np.flatnonzero(beyond)
        for label in np.unique(cell_labels):
            members = beyond_index[cell_labels == label]
            if len(members) < min_cells:
                continue
            extreme = members[np.argmax(sign * mean[members])]
            defects.append(Defect(center=centroid[extreme], depth_mm=float(mean[extreme]),
                                  area_mm2=float(len(members) * cell_mm**2), points=int(counts[members].sum())))
    return sorted(defects, key=lambda defect: -abs(defect.depth_mm))


def deviation_colors(deviation: np.ndarray, tolerance: tuple[float, float]) -> np.ndarray:
    """RGB (N, 3) uint8 on a diverging map (blue missing material, red excess) spanning the tolerance; NaN grey."""
    from services.fusion.colormap import UNSEEN_COLOR, colormap_lut

    lut = colormap_lut("coolwarm")
    span = max(abs(tolerance[0]), abs(tolerance[1]))
    rgb = np.empty((len(deviation), 3), dtype=np.uint8)
    rgb[...] = UNSEEN_COLOR
    finite = np.isfinite(deviation)
    scaled = np.clip((deviation[finite] / span + 1) / 2, 0, 1)
    rgb[finite] = lut[np.round(scaled * 255).astype(np.intp)]
    return rgb
