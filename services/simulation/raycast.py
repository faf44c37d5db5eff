"""Closest-hit ray casting against a scene: exact analytic planes, spheres and cylinders, and triangle meshes."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.simulation.scene import Cylinder, Mesh, Plane, Scene, Sphere

_CHUNK = 1 << 18
_LEAF_SIZE = 4
_STACK_DEPTH = 64


@dataclass(frozen=True)
class Hits:
    """Closest hit of each ray.

    Attributes
    ----------
    distance : (N,) array
        Distance from the ray origin in mm (the ray parameter of the unit direction); inf on a miss.
    points : (N, 3) array
        World hit points; NaN on a miss.
    normals : (N, 3) array
        Unit surface normals turned to face the incoming ray (n . d < 0); NaN on a miss.
    surface : (N,) int array
        Index into ``scene.surfaces``; -1 on a miss.
    """

    distance: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    surface: np.ndarray


def cast_rays(scene: Scene, origins: np.ndarray, directions: np.ndarray, t_min: float = 1e-6) -> Hits:
    """Find where each ray first meets the scene.

    Parameters
    ----------
    scene : Scene
        Surfaces to intersect (meshes must be loaded).
    origins : (3,) or (N, 3) array
        Ray origins in world mm: one shared origin or one per ray.
    directions : (N, 3) array
        Ray directions (normalised internally).
    t_min : float
        Hits closer than this distance (mm) are ignored, so rays leaving a surface do not re-hit it.

    Returns
    -------
    Hits
        Closest hit per ray.

    Notes
    -----
    A ray X(s) = o + s d (|d| = 1) meets a plane n . (X - c) = 0 at s = n . (c - o) / n . d, a sphere
    |X - c| = r at s = -b -/+ sqrt(b^2 - |o - c|^2 + r^2) with b = d . (o - c), and a cylinder side where
    the components perpendicular to the axis satisfy |o_perp + s d_perp| = r (caps as disks), all in
    closed form, so hits are exact to rounding. Triangles use the Moller-Trumbore test [1]_ inside a
    bounding-volume hierarchy. Rays that pass outside a surface's bounding sphere skip its exact test.

    References
    ----------
    .. [1] T. Moller and B. Trumbore, "Fast, minimum storage ray-triangle intersection",
       Journal of Graphics Tools 2(1), 1997.
    """
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3); got {directions.shape}.")
    norms = np.sqrt(np.einsum("ij,ij->i", directions, directions))[:, None]
    if not np.all(np.isfinite(norms)) or np.any(norms == 0):
        raise ValueError("Every ray direction must be finite and non-zero.")
    directions = directions / norms
    origins = np.asarray(origins, dtype=np.float64)
    if origins.shape == (3,):
        origins = np.broadcast_to(origins, directions.shape)
    elif origins.shape != directions.shape:
        raise ValueError(f"origins must have shape (3,) or {directions.shape}; got {origins.shape}.")

    meshes = {index: _mesh_bvh(surface) for index, surface in enumerate(scene.surfaces) if isinstance(surface, Mesh)}
    count = len(directions)
    distance = np.full(count, np.inf)
    normals = np.full((count, 3), np.nan)
    surface = np.full(count, -1, dtype=np.int64)
    bounds = [_bounding_sphere(shape) for shape in scene.surfaces]
    for start in range(0, count, _CHUNK):
        chunk = slice(start, start + _CHUNK)
        o, d = origins[chunk], directions[chunk]
        chunk_distance, chunk_normals, chunk_surface = distance[chunk], normals[chunk], surface[chunk]
        for index, shape in enumerate(scene.surfaces):
            rays = np.flatnonzero(_may_hit(*bounds[index], o, d, t_min))
            if index in meshes:
                s, n = _intersect_mesh(meshes[index], o[rays], d[rays], t_min)
            else:
                s, n = _ANALYTIC[type(shape)](shape, o[rays], d[rays], t_min)
            closer = s < chunk_distance[rays]
            chunk_distance[rays[closer]] = s[closer]
            chunk_normals[rays[closer]] = n[closer]
            chunk_surface[rays[closer]] = index
    hit = surface >= 0
    with np.errstate(invalid="ignore"):
        points = np.where(hit[:, None], origins + distance[:, None] * directions, np.nan)
    facing_away = np.einsum("ij,ij->i", normals, directions) > 0
    normals[facing_away] *= -1
    return Hits(distance=distance, points=points, normals=normals, surface=surface)


_BVH_KEPT = 8
_bvh_cache: dict[int, tuple[Mesh, _Bvh]] = {}


def _mesh_bvh(mesh: Mesh) -> _Bvh:
    """The mesh's BVH, built once per mesh object (a render casts several batches of rays at one scene, and
    building takes seconds for 10^5 triangles); the last few are kept, with the mesh so that its id stays its own."""
    kept = _bvh_cache.get(id(mesh))
    if kept is not None and kept[0] is mesh:
        return kept[1]
    bvh = _build_bvh(mesh.triangles())
    if len(_bvh_cache) >= _BVH_KEPT:
        _bvh_cache.pop(next(iter(_bvh_cache)))
    _bvh_cache[id(mesh)] = (mesh, bvh)
    return bvh


def _bounding_sphere(shape) -> tuple[np.ndarray, float]:
    """Centre and radius of a sphere enclosing the surface."""
    if isinstance(shape, Mesh):
        corners = shape.triangles().reshape(-1, 3)
        low, high = corners.min(axis=0), corners.max(axis=0)
        return (low + high) / 2, float(np.linalg.norm(high - low)) / 2
    if isinstance(shape, Plane):
        return np.asarray(shape.center), float(np.hypot(*shape.size)) / 2
    if isinstance(shape, Cylinder):
        return np.asarray(shape.center), float(np.hypot(shape.radius, shape.length / 2))
    return np.asarray(shape.center), shape.radius


def _may_hit(centre: np.ndarray, radius: float, o: np.ndarray, d: np.ndarray, t_min: float) -> np.ndarray:
    """Rays (unit d) passing within ``radius`` of ``centre`` ahead of t_min: a cheap cull before exact tests."""
    to_centre = centre - o
    along = np.einsum("ij,ij->i", to_centre, d)
    squared = np.einsum("ij,ij->i", to_centre, to_centre)
    return (squared - along * along <= radius * radius * (1 + 1e-9)) & (along + radius >= t_min)


def _nearest_root(a: np.ndarray, half_b: np.ndarray, c: np.ndarray, accept, t_min: float) -> np.ndarray:
    """Smallest root s >= t_min of a s^2 + 2 half_b s + c = 0 for which ``accept(s)`` holds; inf if none."""
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(half_b * half_b - a * c)
        best = np.full(a.shape, np.inf)
        for s in ((-half_b + root) / a, (-half_b - root) / a):
            valid = np.isfinite(s) & (s >= t_min) & accept(s)
            best = np.where(valid & (s < best), s, best)
    return best


def _intersect_plane(plane: Plane, o: np.ndarray, d: np.ndarray, t_min: float) -> tuple[np.ndarray, np.ndarray]:
    normal, u_axis, v_axis = plane.frame()
    center = np.asarray(plane.center)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (center @ normal - o @ normal) / (d @ normal)
        along_u = o @ u_axis - center @ u_axis + s * (d @ u_axis)
        along_v = o @ v_axis - center @ v_axis + s * (d @ v_axis)
        inside = (np.abs(along_u) <= plane.size[0] / 2) & (np.abs(along_v) <= plane.size[1] / 2)
    s = np.where(np.isfinite(s) & (s >= t_min) & inside, s, np.inf)
    return s, np.broadcast_to(normal, d.shape)


def _intersect_sphere(sphere: Sphere, o: np.ndarray, d: np.ndarray, t_min: float) -> tuple[np.ndarray, np.ndarray]:
    center = np.asarray(sphere.center)
    offset = o - center
    s = _nearest_root(np.ones(len(d)), np.einsum("ij,ij->i", offset, d),
                      np.einsum("ij,ij->i", offset, offset) - sphere.radius**2, lambda s: True, t_min)
    with np.errstate(invalid="ignore"):
        normals = (offset + s[:, None] * d) / sphere.radius
    return s, normals


def _intersect_cylinder(cylinder: Cylinder, o: np.ndarray, d: np.ndarray,
                        t_min: float) -> tuple[np.ndarray, np.ndarray]:
    axis = np.asarray(cylinder.axis, dtype=np.float64)
    axis /= np.linalg.norm(axis)
    center = np.asarray(cylinder.center)
    half_length = cylinder.length / 2
    offset = o - center
    height_o, height_d = offset @ axis, d @ axis
    offset_perp = offset - height_o[:, None] * axis
    d_perp = d - height_d[:, None] * axis
    s = _nearest_root(np.einsum("ij,ij->i", d_perp, d_perp), np.einsum("ij,ij->i", offset_perp, d_perp),
                      np.einsum("ij,ij->i", offset_perp, offset_perp) - cylinder.radius**2,
                      lambda s: np.abs(height_o + s * height_d) <= half_length, t_min)
    with np.errstate(invalid="ignore"):
        normals = (offset_perp + s[:, None] * d_perp) / cylinder.radius
    if cylinder.capped:
        for side in (-1.0, 1.0):
            with np.errstate(divide="ignore", invalid="ignore"):
                s_cap = (side * half_length - height_o) / height_d
                radial = offset_perp + s_cap[:, None] * d_perp
            on_cap = (np.isfinite(s_cap) & (s_cap >= t_min)
                      & (np.einsum("ij,ij->i", radial, radial) <= cylinder.radius**2) & (s_cap < s))
            s = np.where(on_cap, s_cap, s)
            normals = np.where(on_cap[:, None], side * axis, normals)
    return s, normals


_ANALYTIC = {Plane: _intersect_plane, Sphere: _intersect_sphere, Cylinder: _intersect_cylinder}


@dataclass(frozen=True)
class _Bvh:
    """Bounding-volume hierarchy over triangles: node boxes, children (-1 for leaves) and leaf ranges."""

    corner: np.ndarray  # (T, 3) first vertex per triangle, in leaf order
    edge1: np.ndarray  # (T, 3)
    edge2: np.ndarray  # (T, 3)
    normal: np.ndarray  # (T, 3) unit face normal
    box_low: np.ndarray  # (M, 3)
    box_high: np.ndarray  # (M, 3)
    left: np.ndarray  # (M,) child node or -1
    right: np.ndarray  # (M,)
    first: np.ndarray  # (M,) first triangle of a leaf
    count: np.ndarray  # (M,) triangles in a leaf, 0 for inner nodes


def _build_bvh(triangles: np.ndarray) -> _Bvh:
    """Median-split BVH: each node splits its triangles at the median centroid along its widest axis."""
    centroids = triangles.mean(axis=1)
    low_all, high_all = triangles.min(axis=1), triangles.max(axis=1)
    order = np.arange(len(triangles))
    box_low, box_high, left, right, first, count = [], [], [], [], [], []
    pending = [(0, len(triangles), -1, False)]  # (start, stop, parent, is_right_child)
    while pending:
        start, stop, parent, is_right = pending.pop()
        node = len(left)
        members = order[start:stop]
        box_low.append(low_all[members].min(axis=0))
        box_high.append(high_all[members].max(axis=0))
        left.append(-1)
        right.append(-1)
        first.append(start)
        count.append(0)
        if parent >= 0:
            (right if is_right else left)[parent] = node
        if stop - start <= _LEAF_SIZE:
            count[node] = stop - start
            continue
        spread = np.ptp(centroids[members], axis=0)
        order[start:stop] = members[np.argsort(centroids[members, np.argmax(spread)], kind="stable")]
        middle = (start + stop) // 2
        pending.append((middle, stop, node, True))
        pending.append((start, middle, node, False))
    ordered = triangles[order]
    edge1, edge2 = ordered[:, 1] - ordered[:, 0], ordered[:, 2] - ordered[:, 0]
    normal = np.cross(edge1, edge2)
    with np.errstate(invalid="ignore"):  # degenerate triangles get NaN normals and are never hit
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return _Bvh(np.ascontiguousarray(ordered[:, 0]), edge1, edge2, normal, np.array(box_low), np.array(box_high),
                np.array(left), np.array(right), np.array(first), np.array(count))


def _intersect_mesh(bvh: _Bvh, o: np.ndarray, d: np.ndarray, t_min: float) -> tuple[np.ndarray, np.ndarray]:
    s = np.full(len(d), np.inf)
    hit_triangle = np.full(len(d), -1, dtype=np.int64)
    _traverse_bvh(o, np.ascontiguousarray(d), t_min, bvh.corner, bvh.edge1, bvh.edge2, bvh.box_low, bvh.box_high,
                  bvh.left, bvh.right, bvh.first, bvh.count, s, hit_triangle)
    normals = np.where((hit_triangle >= 0)[:, None], bvh.normal[np.maximum(hit_triangle, 0)], np.nan)
    return s, normals


# Hand-written with numba: a per-ray tree walk has data-dependent branching that numpy cannot vectorise,
# and brute-force Moller-Trumbore over all triangles is thousands of times more work for large meshes.
@numba.njit(parallel=True, cache=True, error_model="numpy")
def _traverse_bvh(origins, directions, t_min, corner, edge1, edge2, box_low, box_high, left, right, first, count,
                  out_s, out_triangle):  # pragma: no cover - compiled
    rays = directions.shape[0]
    block = 4096
    for b in numba.prange((rays + block - 1) // block):
        stack = np.empty(_STACK_DEPTH, np.int64)
        for i in range(b * block, min(rays, (b + 1) * block)):
            ox, oy, oz = origins[i, 0], origins[i, 1], origins[i, 2]
            dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
            ix = 1.0 / dx if dx != 0.0 else 1e300
            iy = 1.0 / dy if dy != 0.0 else 1e300
            iz = 1.0 / dz if dz != 0.0 else 1e300
            best = np.inf
            best_triangle = -1
            stack[0] = 0
            top = 1
            while top > 0:
                top -= 1
                node = stack[top]
                t0x, t1x = (box_low[node, 0] - ox) * ix, (box_high[node, 0] - ox) * ix
                t0y, t1y = (box_low[node, 1] - oy) * iy, (box_high[node, 1] - oy) * iy
                t0z, t1z = (box_low[node, 2] - oz) * iz, (box_high[node, 2] - oz) * iz
                enter = max(min(t0x, t1x), min(t0y, t1y), min(t0z, t1z))
                leave = min(max(t0x, t1x), max(t0y, t1y), max(t0z, t1z))
                if leave < enter or leave < t_min or enter > best:
                    continue
                if count[node] == 0:
                    stack[top] = left[node]
                    stack[top + 1] = right[node]
                    top += 2
                    continue
                for k in range(first[node], first[node] + count[node]):
                    e1x, e1y, e1z = edge1[k, 0], edge1[k, 1], edge1[k, 2]
                    e2x, e2y, e2z = edge2[k, 0], edge2[k, 1], edge2[k, 2]
                    px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    if det == 0.0:
                        continue
                    inv = 1.0 / det
                    sx, sy, sz = ox - corner[k, 0], oy - corner[k, 1], oz - corner[k, 2]
                    u = (sx * px + sy * py + sz * pz) * inv
                    if u < 0.0 or u > 1.0:
                        continue
                    qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
                    v = (dx * qx + dy * qy + dz * qz) * inv
                    if v < 0.0 or u + v > 1.0:
                        continue
                    s = (e2x * qx + e2y * qy + e2z * qz) * inv
                    if t_min <= s < best:
                        best = s
                        best_triangle = k
            out_s[i] = best
            out_triangle[i] = best_triangle
