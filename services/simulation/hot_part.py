"""A part as it is hot: its nominal cold mesh, dents or bulges of known size, expanded by a temperature field.

The simulator's model of the hot part (the ground truth of the inspection experiments): the true
cold part is the nominal mesh with smooth dents or bulges, placed in the world by a pose; every
point X of it moves away from the part's centre c by the integral of (1 + eps(T)) along the segment
from c, with T a volumetric temperature field in cold part coordinates,

    X_hot = c + (X - c) int_0^1 (1 + eps(T(c + s (X - c)))) ds,

eps the material's thermal elongation from 20 degC. A uniform field is a uniform scaling; a
gradient or a hot spot is not. ``simulated_field`` then measures it as the station does: camera
pixels where the projector lights the part, with structured-light noise along each line of sight,
and the temperature where the thermal camera sees the point, with its noise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from services.geometry.camera import normalized_coordinates, pixel_grid
from services.geometry.camera_model import CameraModel
from services.inspection.materials import Material
from services.open3d_loader import open3d
from services.simulation.scene import Mesh
from services.simulation.thermal import SurfaceTemperature, ThermalEffects

_NODES = 8


def cylinder_mesh(radius: float, length: float, segments: int = 360, rings: int | None = None,
                  cap_rings: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A closed cylinder along x centred at the origin, outward triangles; vertices (V, 3), triangles (T, 3).

    ``rings`` divisions along the side (default about one per segment width) and ``cap_rings``
    concentric rings on each end (default likewise), so dents can be modelled anywhere.
    """
    spacing = 2 * np.pi * radius / segments
    rings = rings or max(1, int(np.ceil(length / spacing)))
    cap_rings = cap_rings or max(1, int(np.ceil(radius / spacing)))
    angles = np.arange(segments) * 2 * np.pi / segments
    circle = np.column_stack([np.cos(angles), np.sin(angles)])
    vertices, triangles = [], []

    def ring(x: float, r: float) -> int:
        vertices.append(np.column_stack([np.full(segments, x), r * circle]))
        return sum(len(v) for v in vertices) - segments

    def band(first: int, second: int, flip: bool) -> None:
        a = first + np.arange(segments)
        b = first + (np.arange(segments) + 1) % segments
        c = second + np.arange(segments)
        d = second + (np.arange(segments) + 1) % segments
        quads = [np.column_stack([a, b, d]), np.column_stack([a, d, c])]
        triangles.extend(q[:, ::-1] if flip else q for q in quads)

    side = [ring(x, radius) for x in np.linspace(-length / 2, length / 2, rings + 1)]
    for first, second in zip(side[:-1], side[1:]):
        band(first, second, flip=True)
    for end, flip in ((-length / 2, False), (length / 2, True)):
        previous = side[0] if end < 0 else side[-1]
        for k in range(cap_rings - 1, 0, -1):
            current = ring(end, radius * k / cap_rings)
            band(previous, current, flip=not flip)
            previous = current
        vertices.append(np.array([[end, 0.0, 0.0]]))
        centre = sum(len(v) for v in vertices) - 1
        a = previous + np.arange(segments)
        b = previous + (np.arange(segments) + 1) % segments
        fan = np.column_stack([a, b, np.full(segments, centre)])
        triangles.append(fan if flip else fan[:, ::-1])
    vertices = np.concatenate(vertices)
    triangles = np.concatenate(triangles).astype(np.int32)
    # turn every triangle outward: along +-x on the end faces, away from the axis on the side
    corners = vertices[triangles]
    centre = corners.mean(axis=1)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    on_end = np.all(np.abs(np.abs(corners[:, :, 0]) - length / 2) < 1e-9, axis=1)
    outward = np.where(on_end[:, None], np.column_stack([np.sign(centre[:, 0]), np.zeros((len(centre), 2))]),
                       np.column_stack([np.zeros(len(centre)), centre[:, 1:]]))
    inward = np.einsum("ij,ij->i", normal, outward) < 0
    triangles[inward] = triangles[inward][:, ::-1]
    return vertices, triangles


def tube_mesh(outer_radius: float, inner_radius: float, length: float, segments: int = 360,
              max_edge_mm: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """An open tube along x centred at the origin (outer and inner walls, annular end faces), outward triangles.

    The profile (x, r) runs round the wall's section: the outer side, the +x end face, the inner side
    and the -x end face, split into edges of at most ``max_edge_mm`` (default the outer arc per segment).
    """
    if not 0 < inner_radius < outer_radius:
        raise ValueError(f"a tube needs 0 < inner radius < outer radius; got {inner_radius} and {outer_radius}")
    step = max_edge_mm or 2 * np.pi * outer_radius / segments
    half = length / 2
    corners = [(-half, outer_radius), (half, outer_radius), (half, inner_radius), (-half, inner_radius)]
    profile = []
    for a, b in zip(corners, corners[1:] + corners[:1]):
        pieces = max(1, int(np.ceil(np.hypot(b[0] - a[0], b[1] - a[1]) / step)))
        profile.extend(np.linspace(a, b, pieces + 1)[:-1])
    profile = np.array(profile)
    angles = np.arange(segments) * 2 * np.pi / segments
    rings = np.stack([np.column_stack([np.full(segments, x), r * np.cos(angles), r * np.sin(angles)])
                      for x, r in profile])
    vertices = rings.reshape(-1, 3)
    j = np.arange(segments)
    k = (j + 1) % segments
    triangles = []
    count = len(profile)
    for ring in range(count):
        a, b = ring * segments + j, ring * segments + k
        nxt = (ring + 1) % count
        c, d = nxt * segments + j, nxt * segments + k
        triangles += [np.column_stack([a, b, d]), np.column_stack([a, d, c])]
    triangles = np.concatenate(triangles).astype(np.int32)
    corners3 = vertices[triangles]
    if np.einsum("ij,ij->i", corners3[:, 0], np.cross(corners3[:, 1], corners3[:, 2])).sum() < 0:
        triangles = triangles[:, ::-1].copy()  # the profile ran the other way round: turn the faces outward
    return vertices, triangles


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of a mesh."""
    corners = vertices[triangles]
    face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, triangles[:, k], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)


@dataclass(frozen=True)
class Bump:
    """A smooth dent (``height_mm`` < 0) or bulge (> 0) on the cold part, part frame.

    The surface moves along its normal by height * exp(-d^2 / (2 sigma^2)), d the distance of the
    vertex from ``center``, so its extreme is ``height_mm`` at ``center``.
    """

    center: tuple[float, float, float]
    sigma_mm: float
    height_mm: float


@dataclass(frozen=True)
class HotPart:
    """A cold part (part frame), where it lies in the world, what it is made of and how hot it is.

    ``temperature`` is a volumetric field in cold part coordinates (degrees C); ``centre`` the
    part-frame point that stays fixed (default the vertices' mean).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: Material
    temperature: SurfaceTemperature
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    bumps: tuple[Bump, ...] = ()
    centre: tuple[float, float, float] | None = None

    def cold_vertices(self) -> np.ndarray:
        """The true cold part: the nominal vertices with the bumps, part frame."""
        vertices = np.asarray(self.vertices, dtype=np.float64)
        if not self.bumps:
            return vertices
        normals = vertex_normals(vertices, self.triangles)
        moved = vertices.copy()
        for bump in self.bumps:
            squared = np.sum((vertices - np.asarray(bump.center)) ** 2, axis=1)
            moved += normals * (bump.height_mm * np.exp(-squared / (2 * bump.sigma_mm**2)))[:, None]
        return moved

    @property
    def fixed_point(self) -> np.ndarray:
        return np.mean(self.vertices, axis=0) if self.centre is None else np.asarray(self.centre, dtype=np.float64)

    def stretch(self, cold_points: np.ndarray) -> np.ndarray:
        """int_0^1 (1 + eps(T(c + s (X - c)))) ds for cold part-frame points (N, 3) (8-point Gauss-Legendre)."""
        c = self.fixed_point
        nodes, weights = np.polynomial.legendre.leggauss(_NODES)
        total = np.zeros(len(cold_points))
        for s, weight in zip((nodes + 1) / 2, weights / 2):
            total += weight * self.material.strain(self.temperature.evaluate(c + s * (cold_points - c)))
        return 1 + total

    def hot_vertices_part(self) -> np.ndarray:
        """The hot part's vertices, part frame."""
        cold = self.cold_vertices()
        c = self.fixed_point
        return c + (cold - c) * self.stretch(cold)[:, None]

    def to_world(self, points: np.ndarray) -> np.ndarray:
        return np.asarray(points) @ self.pose[:3, :3].T + self.pose[:3, 3]

    def surface(self) -> Mesh:
        """The hot part as a scene mesh in the world frame (for ``render_view`` and ``render_thermal``)."""
        return Mesh(vertices=self.to_world(self.hot_vertices_part()).tolist(), faces=self.triangles.tolist())

    def surface_temperature(self, hot_world_points: np.ndarray) -> np.ndarray:
        """True temperature at points of the hot surface (world frame), degrees C."""
        hot = (np.asarray(hot_world_points, dtype=np.float64) - self.pose[:3, 3]) @ self.pose[:3, :3]
        c = self.fixed_point
        cold = hot
        for _ in range(4):  # the stretch varies slowly, so the fixed point converges at once
            cold = c + (hot - c) / self.stretch(cold)[:, None]
        return self.temperature.evaluate(cold)


@dataclass(frozen=True)
class ScanNoise:
    """The station's measurement errors: structured-light noise along each line of sight, thermal noise, bias."""

    structured_light_mm: float = 0.02
    netd_k: float = 0.05
    temperature_bias_k: float = 0.0


@dataclass(frozen=True)
class Backdrop:
    """A flat square wall (world frame) behind the part: its centre, unit normal facing the devices, side
    length and uniform temperature. The camera measures it where the projector lights it, and the thermal
    camera sees it around the part's silhouette."""

    centre: tuple[float, float, float]
    normal: tuple[float, float, float] = (0.0, 0.0, -1.0)
    size_mm: float = 1500.0
    temperature_c: float = 60.0

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Two triangles facing along ``normal``."""
        normal = np.asarray(self.normal, dtype=np.float64)
        normal /= np.linalg.norm(normal)
        helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(helper, normal)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        half = self.size_mm / 2
        corners = np.asarray(self.centre, dtype=np.float64) + half * np.array([-u - v, u - v, u + v, -u + v])
        triangles = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
        if np.dot(np.cross(corners[1] - corners[0], corners[2] - corners[0]), normal) < 0:
            triangles = triangles[:, ::-1].copy()
        return corners, triangles


class _Raycaster:
    """Open3D's Embree ray casting against the hot mesh (world frame): the mesh is large and fine.

    Further meshes (a backdrop) may be added; ``cast`` also says which mesh each ray hit (0 the first).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray,
                 others: tuple[tuple[np.ndarray, np.ndarray], ...] = ()) -> None:
        o3d = open3d()

        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        self._ids = [self._scene.add_triangles(o3d.core.Tensor(np.asarray(v, dtype=np.float32)),
                                               o3d.core.Tensor(np.asarray(t, dtype=np.uint32)))
                     for v, t in ((vertices, triangles), *others)]

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (inf on a miss) and unit normal facing the ray, per unit direction."""
        distance, normals, _ = self.cast_which(origin, directions)
        return distance, normals

    def cast_which(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`cast` and the index of the mesh each ray hit (-1 on a miss)."""
        rays = np.column_stack([np.broadcast_to(origin, directions.shape), directions]).astype(np.float32)
        answer = self._scene.cast_rays(self._o3d.core.Tensor(rays))
        distance = answer["t_hit"].numpy().astype(np.float64)
        normals = answer["primitive_normals"].numpy().astype(np.float64)
        normals *= np.where(np.einsum("ij,ij->i", normals, directions) > 0, -1.0, 1.0)[:, None]
        geometry = answer["geometry_ids"].numpy().astype(np.int64)
        which = np.full(len(distance), -1, dtype=np.int64)
        for index, ident in enumerate(self._ids):
            which[(geometry == ident) & np.isfinite(distance)] = index
        return distance, normals, which


def _scene_of(part: HotPart, backdrop: Backdrop | None) -> _Raycaster:
    return _Raycaster(part.to_world(part.hot_vertices_part()), part.triangles,
                      () if backdrop is None else (backdrop.mesh(),))


def simulated_field(part: HotPart, camera: CameraModel, projector: CameraModel, thermal: CameraModel, rng: np.random.Generator,
                    noise: ScanNoise = ScanNoise(),
                    backdrop: Backdrop | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """What the station measures of a hot part: a temperature field as ``thermofield field`` writes it.

    Parameters
    ----------
    part : HotPart
        The part, its pose and temperature.
    camera, projector, thermal : CameraModel
        The structured-light camera and projector and the thermal camera.
    rng : numpy.random.Generator
        Source of the noise.
    noise : ScanNoise
        Measurement errors.
    backdrop : Backdrop, optional
        A wall behind the part, measured like the part (its points come after the part's).

    Returns
    -------
    field : dict of 1-D arrays
        ``x, y, z`` (world mm), float32 ``temperature`` (NaN where the thermal camera does not see
        the point) for every camera pixel whose centre ray meets the part (or the backdrop) where the
        projector lights it. The temperature is the true one at the point: no mixed pixels (see
        ``simulated_thermal_frame`` for the thermal camera's image, to fuse as the station does).
    truth : (N, 3) array
        The exact hot surface point of each field point (``on_part`` tells the part's from the
        backdrop's).

    Notes
    -----
    Each camera pixel-centre ray is cast against the hot mesh (Open3D's ray casting: the simulator's
    own BVH builder is too slow for meshes of 10^5 triangles); a hit counts as measured when it faces
    the projector, projects into the projector image and the projector's ray reaches it unobstructed.
    The point is moved along its line of sight by N(0, sigma_SL^2). The temperature is the true
    surface temperature plus the bias and N(0, NETD^2) where the thermal camera's ray reaches the
    point and it falls in its image.
    """
    scene = _scene_of(part, backdrop)
    origin = camera.centre
    rays = normalized_coordinates(pixel_grid(camera.width, camera.height), camera.K, camera.dist)
    directions = np.column_stack([rays, np.ones(len(rays))]) @ camera.R
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    distance, normals, which = scene.cast_which(origin, directions)
    hit = np.isfinite(distance)
    order = np.concatenate([np.flatnonzero(hit & (which == 0)), np.flatnonzero(hit & (which > 0))])
    points = origin + distance[order, None] * directions[order]
    normals, directions, on_part = normals[order], directions[order], which[order] == 0
    measured = _reaches(scene, projector, points, normals)
    points, directions, on_part = points[measured], directions[measured], on_part[measured]
    temperature = np.full(len(points), np.nan if backdrop is None else backdrop.temperature_c)
    temperature[on_part] = part.surface_temperature(points[on_part])
    temperature += noise.temperature_bias_k
    temperature += rng.normal(0.0, noise.netd_k, len(points))
    normals = normals[measured]
    seen = _reaches(scene, thermal, points, normals)
    temperature = np.where(seen, temperature, np.nan)
    noisy = points + directions * rng.normal(0.0, noise.structured_light_mm, len(points))[:, None]
    field = {"x": noisy[:, 0].astype(np.float32), "y": noisy[:, 1].astype(np.float32),
             "z": noisy[:, 2].astype(np.float32), "temperature": temperature.astype(np.float32)}
    return field, points


def on_part(part: HotPart, truth: np.ndarray, tolerance_mm: float = 1e-3) -> np.ndarray:
    """Which truth points of ``simulated_field`` lie on the part (not on the backdrop)."""
    hot = (np.asarray(truth, dtype=np.float64) - part.pose[:3, 3]) @ part.pose[:3, :3]
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(part.hot_vertices_part().astype(np.float32)),
                        o3d.core.Tensor(part.triangles.astype(np.uint32)))
    distance = scene.compute_distance(o3d.core.Tensor(hot.astype(np.float32))).numpy()
    return distance <= tolerance_mm + 1e-3


def simulated_thermal_frame(part: HotPart, thermal: CameraModel, rng: np.random.Generator,
                            backdrop: Backdrop | None = None, effects: ThermalEffects = ThermalEffects(),
                            background_c: float = 25.0, temperature_bias_k: float = 0.0) -> np.ndarray:
    """What the thermal camera reads of the hot part (and the backdrop), degrees C: the image to fuse.

    The model of ``services.simulation.thermal.render_thermal`` (sub-pixel rays through the lens
    distortion, radiance averaged over each pixel, the optics' Gaussian blur on radiance, NETD noise,
    the measuring range) with the hot mesh cast by Open3D: pixels on the part's silhouette mix its
    radiance with the backdrop's (or ``background_c`` where a ray meets nothing), as a real camera's do.
    ``temperature_bias_k`` is added to the part's (not the backdrop's) temperature.
    """
    import cv2

    from services.fusion.radiometry import blackbody_counts, blackbody_temperature
    from services.simulation.render import integrate_pixels, subsample_rays

    scene = _scene_of(part, backdrop)
    origin, directions = subsample_rays(thermal, effects.supersample)
    directions = directions / np.linalg.norm(directions, axis=1, keepdims=True)
    distance, _, which = scene.cast_which(np.asarray(origin, dtype=np.float64).reshape(3), directions)
    temperature = np.full(len(distance), background_c)
    hit_part = which == 0
    points = origin.reshape(1, 3) + distance[hit_part, None] * directions[hit_part]
    temperature[hit_part] = part.surface_temperature(points) + temperature_bias_k
    if backdrop is not None:
        temperature[which == 1] = backdrop.temperature_c
    samples = blackbody_counts(temperature, effects.planck).reshape(thermal.height * effects.supersample, -1)
    counts = integrate_pixels(samples, effects.supersample)
    if effects.blur_sigma > 0:
        counts = cv2.GaussianBlur(counts, (0, 0), effects.blur_sigma, borderType=cv2.BORDER_REPLICATE)
    image = blackbody_temperature(counts, effects.planck) + rng.normal(0.0, effects.netd, counts.shape)
    if effects.measuring_range is not None:
        lowest, highest = effects.measuring_range
        image = np.where((image > lowest) & (image < highest), image, np.nan)
    return image.astype(np.float32)


def _reaches(scene: _Raycaster, device: CameraModel, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Points that face the device, fall inside its image and that its rays reach unobstructed."""
    centre = device.centre
    toward = centre - points
    facing = np.einsum("ij,ij->i", normals, toward) > 0
    pixels = device.project(points)
    inside = ((pixels[:, 0] >= -0.5) & (pixels[:, 0] <= device.width - 0.5)
              & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= device.height - 0.5))
    distance = np.linalg.norm(toward, axis=1)
    candidate = np.flatnonzero(facing & inside)
    reached = np.zeros(len(points), dtype=bool)
    along = -toward[candidate] / distance[candidate, None]
    reached[candidate] = scene.cast(centre, along)[0] >= distance[candidate] - 1e-3
    return reached


def billet_pose(tilt_deg: float = 30.0, roll_deg: float = 20.0, centre=(0.0, 20.0, 600.0)) -> np.ndarray:
    """A billet lying before the forging rig (``presets.forging_rig``), its +x end turned toward the devices.

    Part to world: a roll of ``roll_deg`` about the part's axis, then ``tilt_deg`` about world y, so that
    the camera, projector and thermal camera see the side and the +x end face; the centre at ``centre``.
    """
    a, b = np.radians(roll_deg), np.radians(tilt_deg)
    roll = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    tilt = np.array([[np.cos(b), 0.0, np.sin(b)], [0.0, 1.0, 0.0], [-np.sin(b), 0.0, np.cos(b)]])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = tilt @ roll, centre
    return pose


def write_billet_part(directory, diameter: float = 90.0, length: float = 200.0, material: str = "carbon-steel",
                      diameter_tolerance=(-0.3, 0.3), surface_tolerance=(-1.0, 1.0), segments: int = 360) -> Path:
    """Write a billet's nominal mesh (``billet.stl``) and part file (``part.json``) into ``directory``.

    Features: ``body_diameter`` (a cylinder over the middle 160 mm). The billet is symmetric end to
    end, so the alignment cannot tell its ends apart and a feature of one end face would be measured
    on whichever end the view shows; hence no end-face features.
    """
    o3d = open3d()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    vertices, triangles = cylinder_mesh(diameter / 2, length, segments)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(directory / "billet.stl"), mesh)
    half, r = length / 2, diameter / 2
    part = {"version": 1, "name": f"billet-{diameter:g}", "material": material, "nominal": "billet.stl",
            "features": [
                {"name": "body_diameter", "type": "cylinder", "measure": "diameter",
                 "region": {"min": [-0.8 * half, -r - 5, -r - 5], "max": [0.8 * half, r + 5, r + 5]},
                 "nominal": diameter, "tolerance": list(diameter_tolerance)}],
            "surface_tolerance": list(surface_tolerance)}
    path = directory / "part.json"
    path.write_text(json.dumps(part, indent=2))
    return path


def write_tube_part(directory, outer_diameter: float = 90.0, inner_diameter: float = 70.0, length: float = 200.0,
                    material: str = "carbon-steel", diameter_tolerance=(-0.3, 0.3), surface_tolerance=(-1.0, 1.0),
                    segments: int = 360) -> Path:
    """Write an open tube's nominal mesh (``tube.stl``, ``tube_mesh``) and part file (``part.json``).

    Features: ``body_diameter``, the outer cylinder over the middle half of the length (the bore seen
    through an open end reaches no deeper than a diameter's worth at the view angles of the station).
    """
    o3d = open3d()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    vertices, triangles = tube_mesh(outer_diameter / 2, inner_diameter / 2, length, segments)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(directory / "tube.stl"), mesh)
    half, r = length / 2, outer_diameter / 2
    part = {"version": 1, "name": f"tube-{outer_diameter:g}x{inner_diameter:g}", "material": material,
            "nominal": "tube.stl",
            "features": [
                {"name": "body_diameter", "type": "cylinder", "measure": "diameter",
                 "region": {"min": [-0.5 * half, -r - 5, -r - 5], "max": [0.5 * half, r + 5, r + 5]},
                 "nominal": outer_diameter, "tolerance": list(diameter_tolerance)}],
            "surface_tolerance": list(surface_tolerance)}
    path = directory / "part.json"
    path.write_text(json.dumps(part, indent=2))
    return path


def revolved_mesh(profile: list[tuple[float, float]], segments: int = 180,
                  max_edge_mm: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed mesh of revolution about x: ``profile`` is (x, r) from the axis (r = 0) around to the axis
    again; vertices (V, 3), outward triangles (T, 3). Profile edges longer than ``max_edge_mm`` are split."""
    points = [np.asarray(profile[0], dtype=np.float64)]
    for a, b in zip(profile[:-1], profile[1:]):
        pieces = max(1, int(np.ceil(np.hypot(b[0] - a[0], b[1] - a[1]) / max_edge_mm)))
        points.extend(np.linspace(a, b, pieces + 1)[1:])
    profile_points = np.array(points)
    if profile_points[0, 1] != 0 or profile_points[-1, 1] != 0:
        raise ValueError("a profile of revolution starts and ends on the axis (r = 0)")
    angles = np.arange(segments) * 2 * np.pi / segments
    inner = profile_points[1:-1]
    rings = np.stack([np.column_stack([np.full(segments, x), r * np.cos(angles), r * np.sin(angles)])
                      for x, r in inner])  # (rings, segments, 3)
    vertices = np.concatenate([rings.reshape(-1, 3), [[profile_points[0, 0], 0, 0], [profile_points[-1, 0], 0, 0]]])
    first_pole, last_pole = len(vertices) - 2, len(vertices) - 1
    j = np.arange(segments)
    k = (j + 1) % segments
    triangles = [np.column_stack([np.full(segments, first_pole), k, j])]
    for ring in range(len(inner) - 1):
        a, b = ring * segments + j, ring * segments + k
        c, d = (ring + 1) * segments + j, (ring + 1) * segments + k
        triangles += [np.column_stack([a, b, d]), np.column_stack([a, d, c])]
    last = (len(inner) - 1) * segments
    triangles.append(np.column_stack([np.full(segments, last_pole), last + j, last + k]))
    triangles = np.concatenate(triangles).astype(np.int32)
    corners = vertices[triangles]
    if np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() < 0:
        triangles = triangles[:, ::-1].copy()  # the profile ran the other way round: turn the faces outward
    return vertices, triangles


def write_forging_part(directory, segments: int = 180) -> Path:
    """Write the part file (``part.json``) and nominal mesh (``forging.stl``) of ``presets.forging_scene``'s part,
    the simulated station's billet with its flange, into ``directory``.

    The scene is the part as it is hot; the nominal is its cold shape: the billet (radius 55 mm, 220 mm
    long, axis x) and the coaxial flange (radius 80 mm, 24 mm long, 95 mm from the billet's centre toward
    -x) shrunk about the billet's centre by 1 + eps(1040 degC) of carbon steel (the billet's core
    temperature in ``thermal.forging_temperatures``). The flange is cooler (about 960 degC), so its cold
    equivalent lies about 0.15 mm inside this nominal. Features: ``body_diameter`` over the billet between
    the flange and the +x end, whose nominal is the shrunk diameter rounded to 0.01 mm (tolerance
    +-0.5 mm); surface tolerance +-1 mm.
    """
    from services.inspection.materials import builtin_material

    o3d = open3d()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    scale = 1.0 / (1.0 + float(builtin_material("carbon-steel").strain(np.array([1040.0]))[0]))
    profile = [(110.0, 0.0), (110.0, 55.0), (-83.0, 55.0), (-83.0, 80.0), (-107.0, 80.0), (-107.0, 55.0),
               (-110.0, 55.0), (-110.0, 0.0)]
    vertices, triangles = revolved_mesh([(x * scale, r * scale) for x, r in profile], segments)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(directory / "forging.stl"), mesh)
    r = 55.0 * scale
    part = {"version": 1, "name": "forging-station-billet", "material": "carbon-steel", "nominal": "forging.stl",
            "features": [
                {"name": "body_diameter", "type": "cylinder", "measure": "diameter",
                 "region": {"min": [-60.0, -r - 5, -r - 5], "max": [95.0, r + 5, r + 5]},
                 "nominal": round(2 * r, 2), "tolerance": [-0.5, 0.5]}],
            "surface_tolerance": [-1.0, 1.0]}
    path = directory / "part.json"
    path.write_text(json.dumps(part, indent=2))
    return path


def _split_polyline(points: list[tuple[float, float]], max_edge_mm: float, closed: bool) -> np.ndarray:
    """The polyline's vertices with every edge longer than ``max_edge_mm`` split evenly (closed: last to first too)."""
    corners = [np.asarray(p, dtype=np.float64) for p in points]
    if closed:
        corners.append(corners[0])
    result = [corners[0]]
    for a, b in zip(corners[:-1], corners[1:]):
        pieces = max(1, int(np.ceil(np.linalg.norm(b - a) / max_edge_mm)))
        result.extend(np.linspace(a, b, pieces + 1)[1:])
    return np.array(result[:-1] if closed else result)


def revolved_loop_mesh(profile: list[tuple[float, float]], segments: int = 180,
                       max_edge_mm: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed mesh of revolution about x with a hole along the axis (a tube, a ring, a washer).

    ``profile`` is a closed polygon of (x, r) points, every r > 0 (the last point joins the first);
    vertices (V, 3), outward triangles (T, 3). Profile edges longer than ``max_edge_mm`` are split.
    """
    loop = _split_polyline(profile, max_edge_mm, closed=True)
    if len(loop) < 3 or np.any(loop[:, 1] <= 0):
        raise ValueError("a ring's profile is a closed polygon of at least 3 points off the axis (every r > 0)")
    angles = np.arange(segments) * 2 * np.pi / segments
    vertices = np.stack([np.column_stack([np.full(segments, x), r * np.cos(angles), r * np.sin(angles)])
                         for x, r in loop]).reshape(-1, 3)
    j = np.arange(segments)
    k = (j + 1) % segments
    triangles = []
    for ring in range(len(loop)):
        following = (ring + 1) % len(loop)
        a, b = ring * segments + j, ring * segments + k
        c, d = following * segments + j, following * segments + k
        triangles += [np.column_stack([a, b, d]), np.column_stack([a, d, c])]
    triangles = np.concatenate(triangles).astype(np.int32)
    corners = vertices[triangles]
    if np.einsum("ij,ij->i", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])).sum() < 0:
        triangles = triangles[:, ::-1].copy()  # the loop ran the other way round: turn the faces outward
    return vertices, triangles


def box_mesh(size: tuple[float, float, float], max_edge_mm: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed box of ``size`` (x, y, z extents, mm) centred at the origin, each face a grid of triangles
    no longer than about ``max_edge_mm``; vertices shared along the edges (V, 3), outward triangles (T, 3)."""
    half = np.asarray(size, dtype=np.float64) / 2
    if half.shape != (3,) or np.any(half <= 0):
        raise ValueError(f"a box's size is three positive extents; got {size}")
    vertices, triangles = [], []
    for axis in range(3):
        u_axis, v_axis = (axis + 1) % 3, (axis + 2) % 3
        nu = max(1, int(np.ceil(2 * half[u_axis] / max_edge_mm)))
        nv = max(1, int(np.ceil(2 * half[v_axis] / max_edge_mm)))
        grid_u, grid_v = np.meshgrid(np.linspace(-half[u_axis], half[u_axis], nu + 1),
                                     np.linspace(-half[v_axis], half[v_axis], nv + 1), indexing="ij")
        for side in (-1.0, 1.0):
            face = np.zeros((nu + 1, nv + 1, 3))
            face[..., axis], face[..., u_axis], face[..., v_axis] = side * half[axis], grid_u, grid_v
            first = sum(len(v) for v in vertices)
            vertices.append(face.reshape(-1, 3))
            index = first + np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
            a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, 1:].ravel()
            quads = np.concatenate([np.column_stack([a, b, d]), np.column_stack([a, d, c])])
            triangles.append(quads if side > 0 else quads[:, ::-1])
    vertices = np.concatenate(vertices)
    # weld the copies of each edge vertex so that the box is closed (bumps then move shared vertices alike)
    unique, inverse = np.unique(np.round(vertices, 9), axis=0, return_inverse=True)
    triangles = inverse.reshape(-1)[np.concatenate(triangles)].astype(np.int32)
    return unique, triangles


def shaft_mesh(diameter: float, length: float, ovality: float = 0.0, segments: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """A closed shaft along x centred at the origin whose cross-section is an ellipse: diameters
    ``diameter + ovality / 2`` along y and ``diameter - ovality / 2`` along z (their difference, Dmax - Dmin,
    is ``ovality``); ``cylinder_mesh`` scaled across its axis, outward triangles."""
    if not 0 <= ovality < diameter:
        raise ValueError(f"a shaft's ovality lies in [0, diameter); got {ovality} for a diameter of {diameter}")
    vertices, triangles = cylinder_mesh(diameter / 2, length, segments)
    vertices[:, 1] *= (diameter + ovality / 2) / diameter
    vertices[:, 2] *= (diameter - ovality / 2) / diameter
    return vertices, triangles


def write_shaft_part(directory, diameter: float = 90.0, length: float = 300.0, material: str = "carbon-steel",
                     diameter_tolerance=(-0.3, 0.3), ovality_tolerance=(0.0, 0.3), length_tolerance=(-1.0, 1.0),
                     surface_tolerance=(-1.0, 1.0), segments: int = 360) -> Path:
    """Write a shaft's nominal mesh (``shaft.stl``, a round ``shaft_mesh``) and part file (``part.json``) into
    ``directory``: the part a station of heads all round it inspects (docs/inspection.md, "All round").

    Features: ``body_diameter`` and ``body_ovality`` (the cylinder over the middle 80 % of the length),
    ``face_a`` and ``face_b`` (the end faces, planes inside 0.65 of the radius so that no point of the side
    falls in their regions) and ``length`` (the distance between the faces). A view from one side shows
    one end face at most; a station all round the part shows both. The length's default tolerance, +-1 mm,
    is about three times its expanded uncertainty at 1000 degC (0.34 mm, mostly the temperature's over
    300 mm): at +-0.5 mm few good parts could be proven OK.
    """
    o3d = open3d()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    vertices, triangles = shaft_mesh(diameter, length, 0.0, segments)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(directory / "shaft.stl"), mesh)
    half, r = length / 2, diameter / 2
    body = {"min": [-0.8 * half, -r - 5, -r - 5], "max": [0.8 * half, r + 5, r + 5]}
    face = 0.65 * r

    def end(x: float) -> dict:
        return {"min": [x - 1.5, -face, -face], "max": [x + 1.5, face, face]}

    part = {"version": 1, "name": f"shaft-{diameter:g}x{length:g}", "material": material, "nominal": "shaft.stl",
            "features": [
                {"name": "body_diameter", "type": "cylinder", "measure": "diameter", "region": body,
                 "nominal": diameter, "tolerance": list(diameter_tolerance)},
                {"name": "body_ovality", "type": "cylinder", "measure": "ovality", "region": body,
                 "nominal": 0.0, "tolerance": list(ovality_tolerance)},
                {"name": "face_a", "type": "plane", "region": end(-half)},
                {"name": "face_b", "type": "plane", "region": end(half)},
                {"name": "length", "type": "distance", "between": ["face_a", "face_b"], "nominal": length,
                 "tolerance": list(length_tolerance)}],
            "surface_tolerance": list(surface_tolerance)}
    path = directory / "part.json"
    path.write_text(json.dumps(part, indent=2))
    return path


def hot_shaft(diameter: float = 90.0, length: float = 300.0, ovality: float = 0.0,
              temperature: SurfaceTemperature | None = None, bumps: tuple[Bump, ...] = (),
              material: str = "carbon-steel", pose: np.ndarray | None = None, segments: int = 360) -> HotPart:
    """A shaft of true cold ``diameter``, ``length`` and ``ovality`` (``shaft_mesh``) with its dents or bulges,
    hot as ``temperature`` (default a uniform 1000 degC), lying along world x at the origin unless ``pose``."""
    from services.inspection.materials import builtin_material

    vertices, triangles = shaft_mesh(diameter, length, ovality, segments)
    return HotPart(vertices, triangles, builtin_material(material),
                   SurfaceTemperature(base=1000.0) if temperature is None else temperature,
                   pose=np.eye(4) if pose is None else pose, bumps=tuple(bumps))


def station_heads(count: int = 4, distance_mm: float = 700.0, tilt_deg: float = 30.0) -> np.ndarray:
    """Positions (count, 3) of a station's heads around a part lying along x at the origin, part frame.

    Head k looks at the centre from the azimuth 45 + k 360 / count degrees about x, tilted ``tilt_deg``
    toward +x for even k and toward -x for odd k, so that both end faces are seen (by different heads).
    """
    azimuth = np.radians(45.0 + np.arange(count) * 360.0 / count)
    tilt = np.radians(tilt_deg)
    side = np.where(np.arange(count) % 2 == 0, 1.0, -1.0)
    return distance_mm * np.column_stack([side * np.sin(tilt), np.cos(tilt) * np.cos(azimuth),
                                          np.cos(tilt) * np.sin(azimuth)])


def all_round_field(part: HotPart, rng: np.random.Generator, noise: ScanNoise = ScanNoise(),
                    heads: np.ndarray | None = None, points_per_mm2: float = 4.0,
                    max_view_deg: float = 75.0) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """A merged temperature field of a hot part measured all round by a station of heads: points sampled
    on the hot surface, each with the head that saw it, its temperature and the station's noise.

    Parameters
    ----------
    part : HotPart
        The part (convex but for shallow dents and bulges: nothing hides it from a head it faces).
    rng : numpy.random.Generator
        Source of the sample and the noise.
    noise : ScanNoise
        Structured-light noise along each point's line of sight, NETD and temperature bias.
    heads : (H, 3) array, optional
        The heads' positions, part frame (default ``station_heads()``, four heads).
    points_per_mm2 : float
        Density of the sample on the hot surface (4: a 0.5 mm spacing).
    max_view_deg : float
        A head measures a point whose normal is at most this far from its line of sight.

    Returns
    -------
    field : dict of 1-D arrays
        ``x, y, z`` (world mm, float32), float32 ``temperature`` and uint8 ``head`` (the index of the
        head that measured the point), as a merged station field holds them; points no head sees are
        left out.
    truth : (N, 3) array
        The exact hot surface point of each field point, world frame.

    Notes
    -----
    A point-level model of the merged field, not the station end to end: no patterns, decoding,
    calibration error or merge. The surface is sampled uniformly by area (the triangles drawn with
    probability proportional to their area, barycentric coordinates uniform; numpy rather than Open3D's
    sampler so that the caller's ``rng`` decides the sample). Each point is measured by the head seeing
    it at the smallest angle between its normal and its line of sight (an overlap thinned to its best
    view, not doubled), moved along that line of sight by N(0, sigma_SL^2); its temperature is the true
    surface temperature plus the bias and N(0, NETD^2).
    """
    heads = station_heads() if heads is None else np.asarray(heads, dtype=np.float64)
    vertices = part.hot_vertices_part()
    corners = vertices[part.triangles]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(cross, axis=1) / 2
    count = int(round(points_per_mm2 * area.sum()))
    chosen = rng.choice(len(area), size=count, p=area / area.sum())
    a, b = rng.random(count), rng.random(count)
    flip = a + b > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    picked = corners[chosen]
    points = picked[:, 0] + a[:, None] * (picked[:, 1] - picked[:, 0]) + b[:, None] * (picked[:, 2] - picked[:, 0])
    normals = cross[chosen] / np.maximum(2 * area[chosen], 1e-300)[:, None]
    toward = heads[None, :, :] - points[:, None, :]  # (N, H, 3)
    toward /= np.linalg.norm(toward, axis=2, keepdims=True)
    cosine = np.einsum("nhk,nk->nh", toward, normals)
    best = np.argmax(cosine, axis=1)
    seen = cosine[np.arange(count), best] >= np.cos(np.radians(max_view_deg))
    points, best = points[seen], best[seen]
    sight = toward[np.flatnonzero(seen), best]
    truth = part.to_world(points)
    temperature = (part.surface_temperature(truth) + noise.temperature_bias_k
                   + rng.normal(0.0, noise.netd_k, len(points)))
    noisy = part.to_world(points + sight * rng.normal(0.0, noise.structured_light_mm, len(points))[:, None])
    field = {"x": noisy[:, 0].astype(np.float32), "y": noisy[:, 1].astype(np.float32),
             "z": noisy[:, 2].astype(np.float32), "temperature": temperature.astype(np.float32),
             "head": best.astype(np.uint8)}
    return field, truth
