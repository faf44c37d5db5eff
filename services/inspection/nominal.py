"""The nominal part's surface, prepared once per part: closest points, signed distances, surface samples."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from services.inspection.distance_grid import DistanceGrid, build_distance_grid, sample_distance_grid
from services.open3d_loader import open3d

_SAMPLES = 60000
_COARSE_SAMPLES = 3000
GRID_SPACING_MM = 1.0
GRID_BAND_MM = 1.5
"""Measured points this close to the nominal (after alignment: nearly all of a part's) are read from the grid."""


@dataclass(frozen=True)
class ClosestPoints:
    """Per query point: the nearest surface point, that triangle's outward normal and the signed distance."""

    points: np.ndarray
    normals: np.ndarray
    signed_distance: np.ndarray


@dataclass(eq=False)
class NominalSurface:
    """A closed triangle mesh in the part frame (mm), with an Open3D ray-casting scene for distance queries.

    Triangles are turned outward if the mesh's signed volume is negative, so a positive signed
    distance means material outside the nominal surface and a negative one material missing.
    The signed distance within ``GRID_BAND_MM`` of the surface is also tabulated on a 1 mm grid
    (``build_distance_grid``, built on the first ``signed_distance``), which ``signed_distance`` reads
    instead of querying the mesh.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    _scene: object = field(init=False, repr=False)
    samples: np.ndarray = field(init=False, repr=False)
    sample_normals: np.ndarray = field(init=False, repr=False)
    sample_tree: cKDTree = field(init=False, repr=False)
    coarse_samples: np.ndarray = field(init=False, repr=False)
    coarse_normals: np.ndarray = field(init=False, repr=False)
    coarse_tree: cKDTree = field(init=False, repr=False)
    area: float = field(init=False, repr=False)
    triangle_normals: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        o3d = open3d()

        vertices = np.ascontiguousarray(self.vertices, dtype=np.float64)
        triangles = np.ascontiguousarray(self.triangles, dtype=np.int32)
        corners = vertices[triangles]
        if np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() < 0:
            triangles = np.ascontiguousarray(triangles[:, ::-1])
        self.vertices, self.triangles = vertices, triangles
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(vertices.astype(np.float32)), o3d.core.Tensor(triangles.astype(np.uint32)))
        self._scene = scene
        self.samples, self.sample_normals = _area_samples(vertices, triangles, _SAMPLES)
        self.sample_tree = cKDTree(self.samples)
        # far queries in a dense tree visit many leaves: the alignment's coarse stages use a sparse one
        coarse = np.linspace(0, len(self.samples) - 1, min(_COARSE_SAMPLES, len(self.samples))).astype(np.intp)
        self.coarse_samples, self.coarse_normals = self.samples[coarse], self.sample_normals[coarse]
        self.coarse_tree = cKDTree(self.coarse_samples)
        corners = vertices[triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        with np.errstate(invalid="ignore", divide="ignore"):
            self.triangle_normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        self.area = float(np.linalg.norm(normals, axis=1).sum() / 2)

    @cached_property
    def grid(self) -> DistanceGrid:
        """The tabulated signed distance (a few seconds for a fine mesh: built when first needed, so that
        checking a part file, which only fits its features, does not pay for it)."""
        count = int(np.ceil(8 * self.area / GRID_SPACING_MM**2)) + 1
        dense, _ = _area_samples(self.vertices, self.triangles, count)
        return build_distance_grid(dense, self._exact, GRID_BAND_MM, GRID_SPACING_MM)

    @cached_property
    def centroid(self) -> np.ndarray:
        """Centre of the solid's volume (the divergence theorem over tetrahedra from the origin)."""
        corners = self.vertices[self.triangles]
        volume = np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6
        if abs(volume.sum()) < 1e-9:
            return self.samples.mean(axis=0)
        return (volume[:, None] * corners.sum(axis=1) / 4).sum(axis=0) / volume.sum()


    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (N,) of points in the part frame, as ``closest`` finds them, at a fraction of its cost.

        Notes
        -----
        Read from the distance grid (``sample_distance_grid``) where it is trusted; from the mesh
        (``closest``) beyond the grid's band and in its cells near edges and tight curves.
        """
        points = np.asarray(points, dtype=np.float64)
        distance, needs_exact = sample_distance_grid(self.grid, points)
        if needs_exact.any():
            distance[needs_exact] = self.closest(points[needs_exact]).signed_distance
        return distance

    def signed_distance_gradient(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances (N,) of points in the part frame and the distance's gradients (N, 3) there: for
        a point near the surface, its offset along the outward normal of its closest surface point, and that
        normal (the point-to-plane residual and direction of ICP against the mesh itself).

        Notes
        -----
        Read from the distance grid (``sample_distance_grid``, the gradient of its trilinear interpolant)
        where it is trusted; elsewhere exact (``closest``: (p - q) / d, the triangle's normal on the surface).
        """
        points = np.asarray(points, dtype=np.float64)
        distance, needs_exact, gradient = sample_distance_grid(self.grid, points, gradient=True)
        if needs_exact.any():
            distance[needs_exact], gradient[needs_exact] = self._exact(points[needs_exact])
        return distance, gradient

    def _exact(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances and the distance's gradient, (p - q) / d: the closest triangle's normal only on
        the surface (off an edge or a vertex, q is shared by several triangles and the gradient is neither's)."""
        closest = self.closest(points)
        distance = closest.signed_distance
        with np.errstate(invalid="ignore", divide="ignore"):
            gradient = (points - closest.points) / distance[:, None]
        on_surface = np.abs(distance) < 1e-3  # Open3D's float32 closest point leaves (p - q) / d noise below
        gradient[on_surface] = closest.normals[on_surface]
        return distance, gradient

    def closest(self, points: np.ndarray) -> ClosestPoints:
        """Closest surface points of query points (N, 3) in the part frame, and their signed distances.

        Notes
        -----
        The magnitude is the Euclidean distance to the nearest point q on the mesh (Open3D's
        BVH query); the sign is that of (p - q) . n with n the outward normal of q's triangle.
        """
        o3d = open3d()

        query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
        answer = self._scene.compute_closest_points(query)
        nearest = answer["points"].numpy().astype(np.float64)
        normals = self.triangle_normals[answer["primitive_ids"].numpy().astype(np.intp)]
        offset = np.asarray(points, dtype=np.float64) - nearest
        distance = np.sqrt(np.einsum("ij,ij->i", offset, offset))
        sign = np.where(np.einsum("ij,ij->i", offset, normals) < 0, -1.0, 1.0)
        return ClosestPoints(points=nearest, normals=normals, signed_distance=sign * distance)


def _area_samples(vertices: np.ndarray, triangles: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points spread over the surface in proportion to area (stratified, deterministic), with normals."""
    corners = vertices[triangles]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(cross, axis=1) / 2
    cumulative = np.cumsum(area)
    positions = (np.arange(count) + 0.5) / count * cumulative[-1]
    which = np.minimum(np.searchsorted(cumulative, positions), len(area) - 1)
    rng = np.random.default_rng(0)
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    chosen = corners[which]
    points = chosen[:, 0] + u[:, None] * (chosen[:, 1] - chosen[:, 0]) + v[:, None] * (chosen[:, 2] - chosen[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = cross[which] / np.linalg.norm(cross[which], axis=1, keepdims=True)
    keep = np.isfinite(normals).all(axis=1)
    return points[keep], normals[keep]
