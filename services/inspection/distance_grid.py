"""Signed distance to a surface, tabulated on a narrow-band voxel grid and read by trilinear interpolation."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

MAX_CORNERS = 16_000_000
"""Bound on the dense grid's corners (64 MB of float32 distances): a larger part gets a coarser grid."""


@dataclass(frozen=True)
class DistanceGrid:
    """Signed distances at the corners of a voxel grid near a surface.

    Attributes
    ----------
    origin : (3,) array
        Position of corner (0, 0, 0), mm.
    spacing : float
        Edge of a voxel, mm.
    distance : (nx, ny, nz) float32 array
        Exact signed distance at each corner within the band, NaN elsewhere.
    exact : (nx - 1, ny - 1, nz - 1) bool array
        Cells where interpolation is not trusted to ``tolerance_mm`` (an edge, a corner or a tight
        curve of the surface passes near): points there need an exact query.
    """

    origin: np.ndarray
    spacing: float
    distance: np.ndarray
    exact: np.ndarray


def build_distance_grid(surface_points: np.ndarray, signed_distance: Callable[[np.ndarray], tuple[np.ndarray,
                        np.ndarray]], band_mm: float, spacing_mm: float = 1.0,
                        tolerance_mm: float = 0.01) -> DistanceGrid:
    """Tabulate a surface's signed distance within ``band_mm`` of it.

    Parameters
    ----------
    surface_points : (M, 3) array
        Points on the surface, at most half a voxel apart (e.g. area-weighted samples), mm.
    signed_distance : callable
        Exact query: ``(N, 3)`` points to their signed distances ``(N,)`` and the distance's unit
        gradients ``(N, 3)`` there.
    band_mm : float
        Every point at most this far from the surface gets an interpolated (or exact) distance.
    spacing_mm : float
        Voxel edge; raised if the part's grid would exceed ``MAX_CORNERS`` corners.
    tolerance_mm : float
        Largest interpolation error accepted; cells that may exceed it are marked ``exact``.

    Returns
    -------
    DistanceGrid

    Notes
    -----
    A cell holding a point of the band has its corners within band + sqrt(3) h of the surface, so
    within band + sqrt(3) h + h / 2 + sqrt(3) h / 2 of the corner nearest a surface point (the
    points are about h / 2 apart); only the corners that close to one (a Euclidean distance
    transform of the grid) are queried exactly. Trilinear interpolation of a function
    with Hessian norm kappa errs by at most h^2 kappa / 8 [1]_; the signed distance's Hessian is the
    surface's curvature. A cell is ``exact`` when either estimate of that error exceeds the
    tolerance: h theta / 8, with theta the largest angle between its corners' gradients (the
    curvature over the cell is at most theta / h), or the largest over its corners of
    (|D_xx| + |D_yy| + |D_zz|) / 8, with D the grid's second differences (the pure second
    derivatives times h^2; trilinear interpolation reproduces the mixed ones). Edges, corners and
    the medial surface inside the part, where the gradient turns fast or jumps, always are.

    References
    ----------
    .. [1] C. de Boor, "A Practical Guide to Splines", Springer 1978, ch. II (linear interpolation error).
    """
    surface_points = np.asarray(surface_points, dtype=np.float64)
    low, high = surface_points.min(axis=0), surface_points.max(axis=0)
    extent = high - low + 2 * (band_mm + 4 * spacing_mm)
    spacing = max(spacing_mm, float(np.cbrt(np.prod(extent) / MAX_CORNERS)))
    reach = band_mm / spacing + 1.5 * np.sqrt(3) + 0.5  # in voxels
    margin = int(np.ceil(reach)) + 1
    origin = low - margin * spacing
    shape = tuple(int(n) for n in np.ceil((high - origin) / spacing).astype(int) + margin + 1)

    far = np.ones(shape, dtype=bool)
    index = np.rint((surface_points - origin) / spacing).astype(np.intp)
    far[index[:, 0], index[:, 1], index[:, 2]] = False
    near = ndimage.distance_transform_edt(far) <= reach
    corners = np.flatnonzero(near)
    positions = np.column_stack(np.unravel_index(corners, shape)) * spacing + origin
    values, gradients = signed_distance(positions)

    distance = np.full(shape, np.nan, dtype=np.float32)
    distance.flat[corners] = values
    exact = _untrusted_cells(near, corners, gradients, spacing, tolerance_mm) | _curved_cells(distance, tolerance_mm)
    return DistanceGrid(origin=origin, spacing=spacing, distance=distance, exact=exact)


def _curved_cells(distance: np.ndarray, tolerance_mm: float) -> np.ndarray:
    """Cells with a corner whose second differences bound the interpolation error above the tolerance."""
    curvature = np.zeros(distance.shape, dtype=np.float32)
    for axis in range(3):
        second = np.full(distance.shape, np.nan, dtype=np.float32)
        inner = [slice(None)] * 3
        inner[axis] = slice(1, -1)
        second[tuple(inner)] = np.abs(np.diff(distance, n=2, axis=axis))
        curvature += second
    bad = ~(curvature / 8 <= tolerance_mm)  # a corner without both neighbours on an axis counts as bad
    cells = tuple(n - 1 for n in distance.shape)
    flagged = np.zeros(cells, dtype=bool)
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                flagged |= bad[i:i + cells[0], j:j + cells[1], k:k + cells[2]]
    return flagged


def _untrusted_cells(known: np.ndarray, corners: np.ndarray, gradients: np.ndarray, spacing: float,
                     tolerance_mm: float) -> np.ndarray:
    """Cells whose corners' gradients spread by more than 8 tolerance / h radians (cells with an unknown corner too)."""
    cell_shape = tuple(n - 1 for n in known.shape)
    offsets = [(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    complete = np.ones(cell_shape, dtype=bool)
    for i, j, k in offsets:
        complete &= known[i:i + cell_shape[0], j:j + cell_shape[1], k:k + cell_shape[2]]
    cells = np.column_stack(np.nonzero(complete))
    slot = np.full(known.size, -1, dtype=np.intp)
    slot[corners] = np.arange(len(corners))
    corner_normals = np.stack([gradients[slot[np.ravel_multi_index((cells + offset).T, known.shape)]]
                               for offset in offsets])
    mean = corner_normals.sum(axis=0)
    mean /= np.maximum(np.linalg.norm(mean, axis=-1, keepdims=True), 1e-12)
    lowest_cosine = np.einsum("cni,ni->cn", corner_normals, mean).min(axis=0)
    # the spread across the cell is at most twice the largest angle from the mean
    spread = 2 * np.arccos(np.clip(lowest_cosine, -1.0, 1.0))
    exact = np.ones(cell_shape, dtype=bool)
    exact[tuple(cells.T)] = ~(spacing * spread / 8 <= tolerance_mm)  # a degenerate triangle's NaN gradient too
    return exact


def sample_distance_grid(grid: DistanceGrid, points: np.ndarray, gradient: bool = False) -> tuple[np.ndarray, ...]:
    """Signed distances of points (N, 3) by trilinear interpolation, and where an exact query is needed.

    Parameters
    ----------
    grid : DistanceGrid
    points : (N, 3) array
        Query points, mm, in the grid's frame.
    gradient : bool
        Also return the interpolant's gradient.

    Returns
    -------
    distance : (N,) float64 array
        Interpolated signed distance; NaN for points outside the band.
    needs_exact : (N,) bool array
        Points outside the band or in cells marked ``exact``: their interpolated distance may be off
        by more than the grid's tolerance.
    gradient : (N, 3) float64 array
        With ``gradient``: the interpolant's gradient (nearly the unit normal of the nearest surface
        point where the cell is trusted), NaN outside the band.

    Notes
    -----
    Each point's cell is found once, for its corners and its ``exact`` flag; the interpolation runs
    along z, then y, then x, and its gradient is the derivative of the same trilinear polynomial.
    """
    position = np.asarray(points, dtype=np.float64) - grid.origin
    if grid.spacing != 1.0:
        position /= grid.spacing
    with np.errstate(invalid="ignore"):
        cell = position.astype(np.intp)  # truncation: the floor of the non-negative positions, the only ones inside
    cells = np.array(grid.exact.shape)
    inside = np.ones(len(cell), dtype=bool)
    for axis in range(3):  # column by column: numpy's reduction over the short axis is several times slower
        inside &= (position[:, axis] >= 0) & (cell[:, axis] < cells[axis])
    position -= cell
    fx, fy, fz = position.T
    np.clip(cell, 0, cells - 1, out=cell)  # points outside the grid read any cell: their distance is NaN below
    _, ny, nz = grid.distance.shape
    first = (cell[:, 0] * ny + cell[:, 1]) * nz + cell[:, 2]
    values = grid.distance.ravel()
    corner = [values[first + (i * ny + j) * nz + k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    along_z = [corner[n] + fz * (corner[n + 1] - corner[n]) for n in (0, 2, 4, 6)]
    along_yz = [along_z[m] + fy * (along_z[m + 1] - along_z[m]) for m in (0, 2)]
    distance = along_yz[0] + fx * (along_yz[1] - along_yz[0])
    distance[~inside] = np.nan
    needs_exact = grid.exact.ravel()[(cell[:, 0] * (ny - 1) + cell[:, 1]) * (nz - 1) + cell[:, 2]]
    needs_exact |= np.isnan(distance)
    if not gradient:
        return distance, needs_exact
    step_z = [corner[n + 1] - corner[n] for n in (0, 2, 4, 6)]
    derivative = np.column_stack([
        along_yz[1] - along_yz[0],
        (1 - fx) * (along_z[1] - along_z[0]) + fx * (along_z[3] - along_z[2]),
        (1 - fx) * ((1 - fy) * step_z[0] + fy * step_z[1]) + fx * ((1 - fy) * step_z[2] + fy * step_z[3]),
    ]) / grid.spacing
    derivative[~inside] = np.nan
    return distance, needs_exact, derivative
