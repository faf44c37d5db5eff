"""Surface deviation: signed distances of cold-equivalent points from the nominal surface, summary and defects."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from services.inspection.nominal import NominalSurface
from services.inspection.point_rows import column_range, finite_rows

_DENSE_CELLS = 20_000_000


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
    return nominal.signed_distance(points_part)


def summarize_deviation(deviation: np.ndarray, tolerance: tuple[float, float]) -> DeviationSummary:
    """Mean, standard deviation, extremes and the fraction outside ``tolerance`` of the finite deviations."""
    finite = deviation[np.isfinite(deviation)]
    if len(finite) == 0:
        nan = float("nan")
        return DeviationSummary(0, nan, nan, nan, nan, nan)
    outside = (finite < tolerance[0]) | (finite > tolerance[1])
    return DeviationSummary(points=len(finite), mean=float(finite.mean()), std=float(finite.std()),
                            min=float(finite.min()), max=float(finite.max()), fraction_outside=float(outside.mean()))


@dataclass(frozen=True)
class CellMeans:
    """The deviation map averaged over cubic cells: one entry per occupied cell."""

    shape: tuple[int, int, int]
    keys: np.ndarray  # flat index of each occupied cell in ``shape``
    mean: np.ndarray  # mean deviation of its points, mm
    counts: np.ndarray
    cell_mm: float
    points: np.ndarray  # (N, 3) the binned points, part frame
    point_keys: np.ndarray  # (N,) the flat index of each one's cell

    def centroids(self, cells: np.ndarray) -> np.ndarray:
        """Centroids (K, 3) of the points of some occupied cells (indices into ``keys``), part frame.

        Only the cells asked for are summed (a defect's deepest cell), not every cell of the map.
        """
        wanted, inverse = np.unique(self.keys[np.asarray(cells, dtype=np.intp)], return_inverse=True)
        chosen = np.flatnonzero(np.isin(self.point_keys, wanted))
        slot = np.searchsorted(wanted, self.point_keys[chosen])
        sums = np.column_stack([np.bincount(slot, weights=self.points[chosen, k], minlength=len(wanted))
                                for k in range(3)])
        return (sums / np.bincount(slot, minlength=len(wanted))[:, None])[inverse.ravel()]


def cell_means(points_part: np.ndarray, deviation: np.ndarray, cell_mm: float = 1.0) -> CellMeans:
    """Bin the points with a finite deviation into cubic cells of edge ``cell_mm`` and average each cell.

    Parameters
    ----------
    points_part : (N, 3) array
        Points in the part frame.
    deviation : (N,) array
        Their signed deviations (NaN for points that are not the part's).
    cell_mm : float
        Edge of the cells (the averaging smooths the structured-light noise).

    Returns
    -------
    CellMeans
    """
    finite = np.isfinite(deviation) & finite_rows(points_part)
    if not finite.all():
        points_part, deviation = points_part[finite], deviation[finite]
    if len(deviation) == 0:
        return CellMeans((1, 1, 1), np.zeros(0, np.intp), np.zeros(0), np.zeros(0, np.intp), cell_mm,
                         np.zeros((0, 3)), np.zeros(0, np.intp))
    cells = np.floor(points_part / cell_mm).astype(np.int64)
    low, high = column_range(cells)
    cells -= low
    shape = tuple(int(n) for n in high - low + 1)
    flat = np.ravel_multi_index(cells.T, shape)
    if np.prod(shape) <= _DENSE_CELLS:  # counting in the box's cells is several times faster than sorting
        counts = np.bincount(flat)
        keys = np.flatnonzero(counts)
        mean = np.bincount(flat, weights=deviation)[keys] / counts[keys]
        counts = counts[keys]
    else:
        keys, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
        mean = np.bincount(inverse, weights=deviation) / counts
    return CellMeans(shape, keys, mean, counts, cell_mm, points_part, flat)


MIN_DEFECT_CELLS = 10
"""A patch is a defect (and can decide a verdict) only with at least this many cells: 10 mm^2 of 1 mm cells."""
MIN_DEFECT_POINTS = 20
"""... and at least this many points in them."""


def patches(cells: CellMeans, beyond: np.ndarray, min_cells: int = MIN_DEFECT_CELLS,
            min_points: int = MIN_DEFECT_POINTS) -> list[np.ndarray]:
    """Connected patches of the cells flagged ``beyond`` (a mask over ``cells.keys``), kept where a patch has
    at least ``min_cells`` cells and ``min_points`` points.

    Cells are grouped by 26-connectivity after a one-cell dilation (``scipy.ndimage``), so that the gaps
    of a cloud sparser than the cells do not split a patch. Returns the indices into ``cells.keys`` of
    each patch's cells.
    """
    beyond = np.asarray(beyond, dtype=bool)
    if not beyond.any():
        return []
    # labelled in the box of the cells beyond, with a cell of margin for the dilation
    index = np.column_stack(np.unravel_index(cells.keys[beyond], cells.shape))
    index -= index.min(axis=0) - 1
    grid = np.zeros(tuple(index.max(axis=0) + 2), dtype=bool)
    grid[tuple(index.T)] = True
    # cells one empty cell apart belong together: a cloud sparser than the cells leaves such gaps
    bridged = ndimage.binary_dilation(grid, structure=np.ones((3, 3, 3)))
    labels, _ = ndimage.label(bridged, structure=np.ones((3, 3, 3)))
    cell_labels = labels[tuple(index.T)]
    beyond_index = np.flatnonzero(beyond)
    found = [beyond_index[cell_labels == label] for label in np.unique(cell_labels)]
    return [members for members in found if len(members) >= min_cells and cells.counts[members].sum() >= min_points]


def find_defects(cells: CellMeans, threshold_mm: float, min_cells: int = MIN_DEFECT_CELLS,
                 min_points: int = MIN_DEFECT_POINTS) -> list[Defect]:
    """Dents and bulges: connected patches where the cell-averaged deviation passes +- ``threshold_mm``.

    Parameters
    ----------
    cells : CellMeans
        The deviation map averaged over cells (``cell_means``).
    threshold_mm : float
        A patch is a dent where the mean deviation of its cells is below -threshold, a bulge above.
    min_cells : int
        Smaller patches are noise, stray points or the ragged edge of the view (10 cells of 1 mm: 10 mm^2).
    min_points : int
        Patches of fewer points are stray points, not a defect (``patches``).

    Returns
    -------
    list of Defect
        Deepest first.

    Notes
    -----
    The patches of :func:`patches`. A patch's depth is the extreme cell mean, its centre that cell's
    point centroid, its area the cell count times cell_mm^2.
    """
    defects = []
    for sign in (-1.0, 1.0):
        found = patches(cells, sign * cells.mean > threshold_mm, min_cells, min_points)
        if not found:
            continue
        extremes = [members[np.argmax(sign * cells.mean[members])] for members in found]
        for members, extreme, center in zip(found, extremes, cells.centroids(extremes)):
            defects.append(Defect(center=center, depth_mm=float(cells.mean[extreme]),
                                  area_mm2=float(len(members) * cells.cell_mm**2),
                                  points=int(cells.counts[members].sum())))
    return sorted(defects, key=lambda defect: -abs(defect.depth_mm))


def surface_verdict(cells: CellMeans, tolerance: tuple[float, float], expanded_uncertainty: float | np.ndarray,
                    min_cells: int = MIN_DEFECT_CELLS, min_points: int = MIN_DEFECT_POINTS) -> str:
    """The surface's conformity: ISO 14253-1's rule applied to patches of the cell-averaged deviation map.

    NotOK where a patch (``patches``: ``min_cells`` connected cells holding ``min_points`` points) lies
    wholly beyond a limit by more than the expanded uncertainty U; else NotDecidable where such a patch
    lies beyond a limit less U (the limit within its interval); else OK. Fewer cells, or cells of fewer
    points, decide nothing. ``expanded_uncertainty`` is one U or one per cell; a non-finite U is
    NotDecidable.
    """
    lower, upper = tolerance
    if lower > upper:
        raise ValueError(f"The tolerance's lower limit {lower} lies above its upper limit {upper}.")
    u = np.broadcast_to(np.asarray(expanded_uncertainty, dtype=np.float64), cells.mean.shape)
    if not np.all(u >= 0):
        return "NotDecidable"
    if (patches(cells, cells.mean > upper + u, min_cells, min_points)
            or patches(cells, cells.mean < lower - u, min_cells, min_points)):
        return "NotOK"
    if (patches(cells, cells.mean > upper - u, min_cells, min_points)
            or patches(cells, cells.mean < lower + u, min_cells, min_points)):
        return "NotDecidable"
    return "OK"


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
