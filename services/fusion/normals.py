"""Surface normals of a point cloud by principal component analysis of each point's neighbours.

A few points' normals (those a reconstruction left unknown) are estimated with an exact k-nearest-neighbour
search on a hashed grid over the cloud, in numpy: it touches each cloud point a handful of times, where a
KD tree over the whole cloud costs about 0.1 s to build (and scipy 0.1 s to import). Many normals are
estimated with scipy's cKDTree, imported then.
"""

from __future__ import annotations

import numpy as np

from services.structured_light.row_bands import map_bands, row_bands

# The grid search serves at most this fraction of the cloud's points; more use the KD tree.
_GRID_FRACTION = 1 / 16
# The first grid's cell side in point spacings, and its growth for the queries it leaves unresolved.
_FIRST_CELL_SPACINGS = 3.5
_CELL_GROWTH = 2.0
# Hash table sizes: cells of the queries' blocks (those that collide only add candidates: the search stays
# exact) and of the candidates' lists (colliding cells share a list).
_MARK_BITS, _LIST_BITS = 21, 18
_HASH_PRIMES = (73856093, 19349663, 83492791)  # Teschner et al., VMV 2003
_BLOCK = np.stack(np.meshgrid(*3 * [np.arange(-1, 2)], indexing="ij"), axis=-1).reshape(-1, 3).astype(np.int32)
_QUERY_BATCH = 4096
_POINT_CHUNK = 1 << 16


def estimate_normals(
    points: np.ndarray, viewpoint: np.ndarray, neighbours: int = 12, where: np.ndarray | None = None
) -> np.ndarray:
    """Unit normals of a point cloud, oriented toward a viewpoint.

    Parameters
    ----------
    points : (N, 3) array
        Points, millimetres.
    viewpoint : (3,) array
        A position that sees every point (e.g. the camera that measured the
        cloud); each normal is flipped to face it.
    neighbours : int
        Neighbourhood size, including the point itself (at least 3).
    where : (N,) bool array, optional
        Estimate only these points' normals (neighbours still come from the
        whole cloud); the others are NaN.

    Returns
    -------
    normals : (N, 3) float64 array
        Unit normals; NaN for non-finite points and those not in ``where``.

    Notes
    -----
    The normal is the eigenvector of the smallest eigenvalue of the
    neighbourhood covariance C = 1/k sum (p_i - p_mean)(p_i - p_mean)^T [1]_.
    The k nearest neighbours come from scipy's cKDTree, or, when at most a
    sixteenth of the points is wanted, from a spatial hash grid [2]_ of cells
    of side h: the 27 cells around a query's hold every point within h of it,
    so a query whose k-th candidate lies within h has its exact neighbours
    (the others are searched again with h doubled).

    References
    ----------
    .. [1] H. Hoppe et al., "Surface Reconstruction from Unorganized Points",
       SIGGRAPH 1992.
    .. [2] M. Teschner et al., "Optimized Spatial Hashing for Collision
       Detection of Deformable Objects", VMV 2003.
    """
    points = np.asarray(points)
    if points.dtype not in (np.float32, np.float64):
        points = points.astype(np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3); got {points.shape}.")
    if neighbours < 3:
        raise ValueError(f"At least 3 neighbours are needed to fit a plane; got {neighbours}.")
    normals = np.full(points.shape, np.nan)
    finite = np.isfinite(points).all(axis=1)
    wanted = finite if where is None else finite & np.asarray(where, dtype=bool)
    if wanted.any():
        normals[wanted] = normals_at(points, np.flatnonzero(wanted), viewpoint, neighbours, finite)
    return normals


def normals_at(points: np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray], index: np.ndarray,
               viewpoint: np.ndarray, neighbours: int = 12, finite: np.ndarray | None = None) -> np.ndarray:
    """The (M, 3) normals of the finite points ``index`` as :func:`estimate_normals` gives them (NaN when the
    cloud has fewer than 3 finite points).

    ``points`` is the (N, 3) array or its three (N,) coordinate arrays (a cloud's ``x, y, z``, read without
    stacking them); ``finite`` the points' finite rows, if known.
    """
    columns = _columns(points)
    if finite is None:
        finite = np.isfinite(columns[0]) & np.isfinite(columns[1]) & np.isfinite(columns[2])
    count = int(np.count_nonzero(finite))
    index = np.asarray(index, dtype=np.intp)
    if count < 3:
        return np.full((len(index), 3), np.nan)
    k = min(neighbours, count)
    queries = _gather(columns, index)
    if len(index) <= _GRID_FRACTION * count:
        neighbour_points = _gather(columns, _grid_neighbours(columns, finite, index, k))
    else:
        from scipy.spatial import cKDTree  # imported only here: about 0.1 s

        valid = _gather(columns, np.flatnonzero(finite))
        # sliding-midpoint splits build about 3x faster than median splits and query as fast here
        tree = cKDTree(valid, balanced_tree=False, compact_nodes=False)
        _, nearest = tree.query(queries, k=k, workers=-1)
        neighbour_points = valid[nearest.reshape(len(index), k)]
    neighbourhood = neighbour_points - neighbour_points.mean(axis=1, keepdims=True)
    covariance = np.einsum("nki,nkj->nij", neighbourhood, neighbourhood)
    _, vectors = np.linalg.eigh(covariance)
    estimated = vectors[:, :, 0]
    toward = np.asarray(viewpoint, dtype=np.float64) - queries
    estimated *= np.where(np.einsum("ni,ni->n", estimated, toward) < 0, -1.0, 1.0)[:, None]
    return estimated


def _columns(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    if isinstance(points, tuple):
        return points
    points = np.asarray(points)
    return points[:, 0], points[:, 1], points[:, 2]


def _gather(columns: tuple[np.ndarray, np.ndarray, np.ndarray], index: np.ndarray) -> np.ndarray:
    """float64 (shape of index, 3) coordinates of the points ``index``."""
    out = np.empty(index.shape + (3,))
    for axis, column in enumerate(columns):
        out[..., axis] = column[index]
    return out


def _grid_neighbours(columns, finite: np.ndarray, index: np.ndarray, k: int) -> np.ndarray:
    """(M, k) indices of the k nearest finite points of each point ``index``, nearest first."""
    result = np.empty((len(index), k), dtype=np.intp)
    todo = np.arange(len(index))
    cell = _FIRST_CELL_SPACINGS * _spacing(columns, finite)
    extent = None
    while len(todo):
        found, exact = _grid_search(columns, finite, index[todo], k, cell)
        result[todo[exact]] = found[exact]
        todo = todo[~exact]
        cell *= _CELL_GROWTH
        if len(todo) and extent is None:
            extent = max(float(np.fmax.reduce(column) - np.fmin.reduce(column)) for column in columns)
        if len(todo) and cell > 4 * extent:  # from 1.75 extents every point is a candidate within the margin
            break
    if len(todo):  # an extent of (almost) zero: every point is a candidate
        candidates = np.flatnonzero(finite)
        for query in todo:
            distance = _squared_distances(_gather(columns, candidates), _gather(columns, index[query:query + 1]))
            result[query] = candidates[np.argsort(distance, kind="stable")[:k]]
    return result


def _spacing(columns, finite: np.ndarray) -> float:
    """A guess of the cloud's point spacing: the median distance between consecutive stored points (a
    scanner's cloud is stored in pixel order), or an eighth of the extent when that is not positive."""
    sample = np.flatnonzero(finite[:-1] & finite[1:])[:: max(1, len(finite) // 4096)]
    step = float(np.median(np.sqrt(_squared_distances(_gather(columns, sample + 1), _gather(columns, sample))))) \
        if len(sample) else 0.0
    if step > 0 and np.isfinite(step):
        return step
    extent = max(float(np.fmax.reduce(column[finite]) - np.fmin.reduce(column[finite])) for column in columns)
    return extent / 8 if extent > 0 else 1.0


def _squared_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Squared distances between the rows of two float64 (n, 3) arrays."""
    difference = a - b
    difference *= difference
    return difference[:, 0] + difference[:, 1] + difference[:, 2]


def _cell_hash(columns, cell: float, index: np.ndarray | None = None, offset: np.ndarray | None = None
               ) -> np.ndarray:
    """int32 hash of the grid cells (floor of coordinate / cell) of the points ``index`` (all if None), each
    displaced by the integer ``offset`` (..., 3) cells if given (the result then broadcasts)."""
    mixed = None
    with np.errstate(invalid="ignore", over="ignore"):
        for axis, column in enumerate(columns):
            values = column if index is None else column[index]
            cells = np.floor(values * values.dtype.type(1.0 / cell)).astype(np.int32)  # NaN: any cell
            if offset is not None:
                cells = cells[:, None] + offset[:, axis]
            cells *= np.int32(_HASH_PRIMES[axis])
            mixed = cells if mixed is None else np.bitwise_xor(mixed, cells, out=mixed)
    return mixed


def _grid_search(columns, finite: np.ndarray, index: np.ndarray, k: int, cell: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """k nearest finite points of the points ``index`` among those in the 27 grid cells around each; and
    whether each query's k-th lies within the cell side (then they are its exact k nearest)."""
    block = _cell_hash(columns, cell, index, _BLOCK)  # (M, 27)
    marked = np.zeros(1 << _MARK_BITS, dtype=bool)
    marked[block & ((1 << _MARK_BITS) - 1)] = True

    def candidates_in(rows: slice) -> tuple[np.ndarray, np.ndarray]:
        slots = _cell_hash(tuple(column[rows] for column in columns), cell)
        slots &= (1 << _MARK_BITS) - 1
        chosen = np.flatnonzero(marked[slots] & finite[rows])
        return chosen + rows.start, slots[chosen]

    parts = map_bands(candidates_in, row_bands(len(finite), 1, _POINT_CHUNK))
    candidates = np.concatenate([part[0] for part in parts])
    lists = np.concatenate([part[1] for part in parts]) & ((1 << _LIST_BITS) - 1)
    order = np.argsort(lists, kind="stable")
    candidates = candidates[order]
    sizes = np.bincount(lists, minlength=1 << _LIST_BITS)
    starts = np.cumsum(sizes) - sizes
    block &= (1 << _LIST_BITS) - 1
    block.sort(axis=1)
    coordinates = tuple(np.asarray(column[candidates], dtype=np.float64) for column in columns)
    queries = _gather(columns, index)
    found = np.zeros((len(index), k), dtype=np.intp)
    exact = np.zeros(len(index), dtype=bool)
    for first in range(0, len(index), _QUERY_BATCH):
        batch = slice(first, first + _QUERY_BATCH)
        found[batch], exact[batch] = _nearest_candidates(queries[batch], block[batch], coordinates, starts, sizes,
                                                         k, cell)
    found = candidates[found]
    return found, exact


def _nearest_candidates(queries: np.ndarray, block: np.ndarray, coordinates: tuple[np.ndarray, ...],
                        starts: np.ndarray, sizes: np.ndarray, k: int, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_grid_search` for queries with the (M, 27) sorted list numbers of their blocks, given the
    float64 coordinates of the candidates sorted by list and each list's start and size; the nearest as
    positions among the candidates."""
    counts = sizes[block]
    counts[:, 1:][block[:, 1:] == block[:, :-1]] = 0  # a list met twice in one block: its points once
    # every (query, candidate) pair, query by query
    totals = counts.sum(axis=1)
    counts = counts.ravel()
    offsets = starts[block].ravel() - (np.cumsum(counts) - counts)
    position = np.repeat(offsets, counts)
    position += np.arange(len(position))
    pair_query = np.repeat(np.arange(len(queries)), totals)
    # squared distances, keeping the pairs within the search radius: a query with k of them has its exact
    # neighbours among them (the margin covers the rounding of the cell coordinates)
    distance = np.zeros(len(position))
    for axis, coordinate in enumerate(coordinates):
        difference = coordinate[position]
        difference -= np.ascontiguousarray(queries[:, axis])[pair_query]
        difference *= difference
        distance += difference
    within = distance <= (0.99 * cell) ** 2
    position, pair_query, distance = position[within], pair_query[within], distance[within]
    totals = np.bincount(pair_query, minlength=len(queries))
    found = np.zeros((len(queries), k), dtype=np.intp)
    exact = totals >= k
    query_starts = np.cumsum(totals) - totals
    # the k smallest of each query's distances, in tables of queries with about as many pairs
    width_class = np.ceil(np.log2(np.maximum(totals, k))).astype(np.intp)
    for width in np.unique(width_class[exact]):
        rows = np.flatnonzero(exact & (width_class == width))
        columns_used = int(totals[rows].max())
        table = np.full((len(rows), columns_used), np.inf)
        column = np.arange(columns_used)
        mine = column < totals[rows, None]
        table[mine] = distance[(query_starts[rows, None] + column)[mine]]
        nearest = np.argpartition(table, k - 1, axis=1)[:, :k] if columns_used > k else \
            np.argsort(table, axis=1)[:, :k]
        nearest = np.take_along_axis(nearest, np.argsort(np.take_along_axis(table, nearest, axis=1), axis=1,
                                                         kind="stable"), axis=1)
        found[rows] = position[query_starts[rows, None] + nearest]
    return found, exact
