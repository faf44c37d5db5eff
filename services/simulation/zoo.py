"""The scene zoo: one random rig, hot part, fixtures and back wall per integer seed, with its ground truth.

``zoo_scene(seed)`` draws, deterministically from ``seed``:

- a rig: projector and camera resolutions and focal lengths, the baseline and its direction, the
  camera's vergence and roll, lens distortion of all three devices, the thermal camera's placement,
  resolution and lens, and a random world frame (every pose and surface moved by one rigid motion);
- a hot part of one of ``PART_KINDS`` (the kind is ``PART_KINDS[seed % 7]``, so every run of seven
  seeds holds each once), its size, material, pose and temperature field (gradient and a spot);
- whether it is in tolerance: an out-of-tolerance part has a diameter off by 1.5 to 3 tolerances
  (shafts, billets, flanges, spheres), or a dent or bulge of 2.5 to 4 surface tolerances where the camera and projector see it;
  an in-tolerance part has deviations within 0.4 of its tolerances;
- its part file (docs/part-file.md): the nominal cold mesh, features with tolerances, the surface
  tolerance; the part's true cold feature values;
- fixtures (a support block, posts beside or before the part) and a tilted back wall that catch the
  part's projector shadow and hide some of it from the camera, all cool, with albedo textures;
- the optics (a blue projector through a 450/40 filter, or a white one unfiltered), camera and
  projector blur, the thermal camera's blur and noise.

Surface 0 of ``ZooScene.scene`` is always the part (a triangle mesh); the others are fixtures and the
wall. See docs/simulator.md, "The scene zoo".
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.inspection.materials import builtin_material
from services.open3d_loader import open3d
from services.simulation.hot_part import (Bump, HotPart, box_mesh, revolved_loop_mesh, revolved_mesh,
                                          vertex_normals)
from services.simulation.presets import HOT_STEEL_EMISSIVITY, hot_optics, look_at_rotation
from services.simulation.raycast import cast_rays
from services.simulation.render import CameraEffects, ProjectorEffects
from services.simulation.scene import Albedo, Cylinder, Mesh, Plane, Scene
from services.simulation.temperature import Spot, SurfaceTemperature, TemperatureScene
from services.simulation.thermal import ThermalEffects

PART_KINDS = ("capped_cylinder", "open_tube", "sphere", "box", "ring", "flange", "stepped_shaft")
TUNING_SEEDS = range(0, 100)
"""Seeds on which thresholds and defaults may be chosen; never reported."""
REPORTING_SEEDS = range(1000, 1230)
"""The held-out seeds whose figures are reported (docs/zoo.md): 1000..1199 first, 1200..1229 drawn after them so
that at least 100 good and 100 bad parts are judged."""

_PROJECTOR_SIZES = ((800, 600), (912, 570), (1024, 768), (1280, 800))
_CAMERA_SIZES = ((640, 480), (720, 540), (752, 480), (800, 600))
_THERMAL_SIZES = ((160, 120), (320, 240), (384, 288), (640, 480))
_SEGMENTS = 180
_MAX_EDGE_MM = 3.0


@dataclass(frozen=True)
class ZooTruth:
    """What the zoo knows of its part.

    ``in_tolerance``: whether every feature and the surface are within their tolerances (the verdict
    the inspection should reach: OK if true, NotOK if false). ``features``: each measured feature's
    true cold value (mm). ``deviation``: a sentence saying what was drawn.
    """

    in_tolerance: bool
    features: dict[str, float]
    deviation: str


@dataclass(frozen=True)
class ZooScene:
    """One zoo scene: rig, hot scene and temperatures, the hot part, its part file and its ground truth.

    ``scene.surfaces[0]`` is the part (its hot mesh); ``part_file`` is the part file's JSON (its
    ``nominal`` names ``nominal.stl``, written with the nominal mesh by :meth:`write_part`).
    """

    seed: int
    kind: str
    rig: Rig
    scene: Scene
    temperatures: TemperatureScene
    part: HotPart
    nominal_vertices: np.ndarray = field(repr=False)
    nominal_triangles: np.ndarray = field(repr=False)
    part_file: dict = field(repr=False)
    truth: ZooTruth = field(repr=False)
    camera_effects: CameraEffects = field(repr=False)
    projector_effects: ProjectorEffects = field(repr=False)
    thermal_effects: ThermalEffects = field(repr=False)
    projector_light: str = "blue"
    description: dict = field(default_factory=dict, repr=False)

    def write_part(self, directory: str | Path) -> Path:
        """Write ``part.json`` and ``nominal.stl`` into ``directory``; returns the part file's path."""
        o3d = open3d()
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.nominal_vertices),
                                         o3d.utility.Vector3iVector(self.nominal_triangles))
        mesh.compute_triangle_normals()
        o3d.io.write_triangle_mesh(str(directory / "nominal.stl"), mesh)
        path = directory / "part.json"
        path.write_text(json.dumps(self.part_file, indent=2))
        return path


@dataclass(frozen=True)
class _Shape:
    """A part kind drawn at a size: nominal and true cold meshes, features and their true values."""

    nominal: tuple[np.ndarray, np.ndarray]
    true: tuple[np.ndarray, np.ndarray]
    features: list[dict]
    true_values: dict[str, float]
    deviation: str
    radius: float  # bounding radius about the origin


def _device(kind: str, size: tuple[int, int], focal: float, dist: list[float], R: np.ndarray,
            centre: np.ndarray) -> CameraModel:
    width, height = size
    K = [[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]]
    return CameraModel(kind=kind, width=width, height=height, K=K, dist=dist, R=R.tolist(),
                       t=(-R @ np.asarray(centre, dtype=np.float64)).tolist())


def _distortion(rng: np.random.Generator, k1: tuple[float, float]) -> list[float]:
    return [float(rng.uniform(*k1)), float(rng.uniform(-0.05, 0.05)), float(rng.uniform(-1e-3, 1e-3)),
            float(rng.uniform(-1e-3, 1e-3)), 0.0]


def _aimed(centre: np.ndarray, target: np.ndarray, roll_deg: float) -> np.ndarray:
    """``look_at_rotation`` turned by ``roll_deg`` about the optical axis."""
    c, s = np.cos(np.radians(roll_deg)), np.sin(np.radians(roll_deg))
    roll = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return roll @ look_at_rotation(tuple(centre), tuple(target))


def _revolved(profile: list[tuple[float, float]], loop: bool) -> tuple[np.ndarray, np.ndarray]:
    if loop:
        return revolved_loop_mesh(profile, _SEGMENTS, _MAX_EDGE_MM)
    return revolved_mesh(profile, _SEGMENTS, _MAX_EDGE_MM)


def _cylinder_feature(name: str, x_range: tuple[float, float], radius: float, nominal: float,
                      tolerance: float) -> dict:
    margin = radius + 5.0
    return {"name": name, "type": "cylinder", "measure": "diameter",
            "region": {"min": [x_range[0], -margin, -margin], "max": [x_range[1], margin, margin]},
            "nominal": round(nominal, 4), "tolerance": [-tolerance, tolerance]}


def _draw_shape(kind: str, rng: np.random.Generator, out: bool, size_tolerance: float) -> _Shape:
    """Nominal and true cold shapes of a part kind, part frame (axis x for shapes of revolution)."""
    # an out-of-tolerance size is 1.5..3 tolerances off; an in-tolerance one within 0.4 of it
    off = (rng.uniform(1.5, 3.0) if out else rng.uniform(-0.4, 0.4)) * size_tolerance * rng.choice([-1.0, 1.0])
    radius = float(rng.uniform(25.0, 55.0))
    if kind in ("capped_cylinder", "flange", "stepped_shaft"):
        length = float(rng.uniform(2.0, 4.0) * radius)
        half = length / 2
        if kind == "capped_cylinder":
            pocket = rng.uniform() < 0.5  # a concavity: a pocket in the +x end face
            pocket_r, pocket_depth = radius * rng.uniform(0.3, 0.6), radius * rng.uniform(0.2, 0.5)

            def profile(r: float) -> list[tuple[float, float]]:
                start = [(half - pocket_depth, 0.0), (half - pocket_depth, pocket_r), (half, pocket_r)] if pocket \
                    else [(half, 0.0)]
                return start + [(half, r), (-half, r), (-half, 0.0)]
            body = (-0.8 * half, 0.8 * half)
            text = f"capped cylinder r {radius:.1f} L {length:.1f}" + (" with an end pocket" if pocket else "")
        elif kind == "flange":
            flange_r, flange_t = radius * rng.uniform(1.3, 1.7), rng.uniform(8.0, 25.0)
            flange_x = -half + rng.uniform(0.0, 0.3) * length

            def profile(r: float) -> list[tuple[float, float]]:
                return [(half, 0.0), (half, r), (flange_x + flange_t, r), (flange_x + flange_t, flange_r),
                        (flange_x, flange_r), (flange_x, r), (-half, r), (-half, 0.0)]
            body = (flange_x + flange_t + 0.1 * (half - flange_x - flange_t), half - 0.1 * (half - flange_x - flange_t))
            text = f"flanged shaft r {radius:.1f} L {length:.1f}, flange r {flange_r:.1f} x {flange_t:.1f}"
        else:
            small_r = radius * rng.uniform(0.5, 0.8)
            step_x = float(rng.uniform(-0.2, 0.2) * length)
            third = rng.uniform() < 0.5
            tip_r, tip_x = small_r * rng.uniform(0.5, 0.8), half - rng.uniform(0.1, 0.2) * length

            def profile(r: float) -> list[tuple[float, float]]:
                end = [(half, 0.0), (half, tip_r), (tip_x, tip_r), (tip_x, small_r)] if third else \
                    [(half, 0.0), (half, small_r)]
                return end + [(step_x, small_r), (step_x, r), (-half, r), (-half, 0.0)]
            span = step_x + half
            body = (-half + 0.1 * span, step_x - 0.1 * span)
            text = f"stepped shaft r {radius:.1f}/{small_r:.1f}" + (f"/{tip_r:.1f}" if third else "") + \
                f" L {length:.1f}"
        nominal, true = _revolved(profile(radius), False), _revolved(profile(radius + off / 2), False)
        features = [_cylinder_feature("body_diameter", body, radius, 2 * radius, size_tolerance)]
        values = {"body_diameter": 2 * radius + off}
        bound = float(np.hypot(half, radius * 1.7))
        text += f"; body diameter {off:+.3f} mm from nominal"
    elif kind in ("open_tube", "ring"):
        if kind == "open_tube":
            wall = float(rng.uniform(2.0, 8.0))  # a thin rim at both open ends
            length = float(rng.uniform(1.5, 3.5) * radius)
        else:
            wall = float(rng.uniform(0.3, 0.6) * radius)
            length = float(rng.uniform(0.25, 0.6) * radius)
        half = length / 2

        def profile(r: float) -> list[tuple[float, float]]:
            return [(half, radius - wall), (half, r), (-half, r), (-half, radius - wall)]
        nominal, true = _revolved(profile(radius), True), _revolved(profile(radius + off / 2), True)
        # the feature region cannot leave out the bore, so a tube or ring is judged by its surface alone
        features, values = [], {}
        bound = float(np.hypot(half, radius))
        text = f"{kind.replace('_', ' ')} r {radius:.1f}, wall {wall:.1f}, L {length:.1f}; outer radius {off / 2:+.3f} mm"
    elif kind == "sphere":
        def profile(r: float) -> list[tuple[float, float]]:
            angles = np.linspace(0.0, np.pi, 121)
            arc = [(float(r * np.cos(a)), float(r * np.sin(a))) for a in angles[1:-1]]
            return [(r, 0.0), *arc, (-r, 0.0)]
        nominal, true = _revolved(profile(radius), False), _revolved(profile(radius + off / 2), False)
        margin = radius + 5.0
        features = [{"name": "diameter", "type": "sphere", "measure": "diameter",
                     "region": {"min": [-margin] * 3, "max": [margin] * 3},
                     "nominal": round(2 * radius, 4), "tolerance": [-size_tolerance, size_tolerance]}]
        values = {"diameter": 2 * radius + off}
        bound = radius
        text = f"sphere r {radius:.1f}; diameter {off:+.3f} mm"
    elif kind == "box":
        size = np.array([rng.uniform(2.0, 4.0), rng.uniform(1.0, 2.0), rng.uniform(0.8, 1.5)]) * radius
        nominal = box_mesh(tuple(size), _MAX_EDGE_MM)
        true = box_mesh((size[0] + off, size[1], size[2]), _MAX_EDGE_MM)
        # one view never shows two opposite faces, so no size of a box can be measured: judged by its surface
        features, values = [], {}
        bound = float(np.linalg.norm(size) / 2)
        text = f"box {size[0]:.1f} x {size[1]:.1f} x {size[2]:.1f}; length {off:+.3f} mm"
    else:
        raise ValueError(f"unknown part kind {kind!r}; the zoo's kinds are {', '.join(PART_KINDS)}")
    return _Shape(nominal, true, features, values, text, bound)


def _moved(surface, rotation: np.ndarray, translation: np.ndarray):
    """A scene surface under the rigid motion X -> rotation X + translation."""
    def point(p):
        return (rotation @ np.asarray(p) + translation).tolist()

    def direction(d):
        return (rotation @ np.asarray(d)).tolist()
    if isinstance(surface, Mesh):
        vertices = np.asarray(surface.vertices) @ rotation.T + translation
        return surface.model_copy(update={"vertices": vertices.tolist()})
    if isinstance(surface, Plane):
        return surface.model_copy(update={"center": point(surface.center), "normal": direction(surface.normal),
                                          "u_axis": direction(surface.u_axis)})
    if isinstance(surface, Cylinder):
        return surface.model_copy(update={"center": point(surface.center), "axis": direction(surface.axis)})
    return surface.model_copy(update={"center": point(surface.center)})


def _moved_temperature(temperature: SurfaceTemperature, rotation: np.ndarray,
                       translation: np.ndarray) -> SurfaceTemperature:
    spots = [spot.model_copy(update={"center": (rotation @ np.asarray(spot.center) + translation).tolist()})
             for spot in temperature.spots]
    return temperature.model_copy(update={
        "origin": (rotation @ np.asarray(temperature.origin) + translation).tolist(),
        "gradient": (rotation @ np.asarray(temperature.gradient)).tolist(), "spots": spots})


def _moved_device(device: CameraModel, rotation: np.ndarray, translation: np.ndarray) -> CameraModel:
    """The device's pose after the world moved by X' = rotation X + translation (x_dev = R' X' + t')."""
    R = device.R @ rotation.T
    return CameraModel(kind=device.kind, width=device.width, height=device.height, K=device.K.tolist(),
                       dist=device.dist.tolist(), R=R.tolist(), t=(device.t - R @ translation).tolist())


def _texture(rng: np.random.Generator, base: tuple[float, float], amplitude: tuple[float, float]) -> Albedo:
    return Albedo(base=float(rng.uniform(*base)), texture_amplitude=float(rng.uniform(*amplitude)),
                  feature_size=float(rng.uniform(10.0, 60.0)), seed=int(rng.integers(0, 2**31)))


def _fixture_box(centre: np.ndarray, size: tuple[float, float, float], albedo: Albedo) -> Mesh:
    vertices, triangles = box_mesh(size, max_edge_mm=max(size))
    return Mesh(vertices=(vertices + centre).tolist(), faces=triangles.tolist(), albedo=albedo)


def _visible_bump_centre(rng: np.random.Generator, vertices: np.ndarray, triangles: np.ndarray, pose: np.ndarray,
                         devices: list[np.ndarray], others: list, sigma: float) -> np.ndarray | None:
    """A part-frame vertex whose neighbourhood (1.5 sigma) faces the camera and the projector, and that both
    see past the fixtures; None when there is none."""
    normals = vertex_normals(vertices, triangles) @ pose[:3, :3].T
    world = vertices @ pose[:3, :3].T + pose[:3, 3]
    facing = np.full(len(vertices), np.inf)
    for centre in devices:
        toward = centre - world
        facing = np.minimum(facing, np.einsum("ij,ij->i", normals, toward) / np.linalg.norm(toward, axis=1))
    candidates = rng.permutation(np.flatnonzero(facing > 0.4))[:64]
    if len(candidates) == 0:
        return None
    scene = Scene(surfaces=[Mesh(vertices=world.tolist(), faces=triangles.tolist()), *others])
    seen = np.ones(len(candidates), dtype=bool)
    for centre in devices:
        hits = cast_rays(scene, centre, world[candidates] - centre)
        seen &= (hits.surface == 0) & (hits.distance >= np.linalg.norm(world[candidates] - centre, axis=1) - 0.5)
    for index in candidates[seen]:
        # the same face's vertices near it (a thin wall's far side and a rim's end face move too, unseen)
        near = (np.linalg.norm(world - world[index], axis=1) < 1.5 * sigma) & (normals @ normals[index] > 0.7)
        if (facing[near] > 0.1).all():
            return vertices[index]
    return None


def zoo_scene(seed: int) -> ZooScene:
    """The zoo's scene number ``seed`` (deterministic); see the module docstring for what is drawn."""
    if seed < 0:
        raise ValueError(f"A zoo seed is a non-negative integer; got {seed}.")
    rng = np.random.default_rng(np.random.SeedSequence([0x2005, seed]))
    kind = PART_KINDS[seed % len(PART_KINDS)]

    # the rig, in a frame with the projector at the origin looking along +z
    depth = float(rng.uniform(480.0, 720.0))
    aim = np.array([rng.uniform(-20, 20), rng.uniform(-20, 20), depth])
    projector_size = _PROJECTOR_SIZES[rng.integers(len(_PROJECTOR_SIZES))]
    projector_focal = projector_size[0] * depth / rng.uniform(320.0, 460.0)
    projector = _device("projector", projector_size, projector_focal, _distortion(rng, (-0.05, 0.05)), np.eye(3),
                        np.zeros(3))
    baseline = float(rng.uniform(150.0, 350.0))
    side = rng.choice([-1.0, 1.0])
    elevation = np.radians(rng.uniform(-20.0, 20.0))
    camera_centre = np.array([side * baseline * np.cos(elevation), baseline * np.sin(elevation),
                              rng.uniform(-30.0, 30.0)])
    camera_size = _CAMERA_SIZES[rng.integers(len(_CAMERA_SIZES))]
    camera_focal = camera_size[0] * depth / rng.uniform(240.0, 380.0)
    camera_target = aim + rng.uniform(-40.0, 40.0, 3) * [1, 1, 0]
    camera = _device("camera", camera_size, camera_focal, _distortion(rng, (-0.12, 0.05)),
                     _aimed(camera_centre, camera_target, rng.uniform(-8.0, 8.0)), camera_centre)
    thermal_centre = np.array([rng.uniform(-250.0, 250.0), rng.uniform(-220.0, 220.0), rng.uniform(-60.0, 40.0)])
    while min(np.linalg.norm(thermal_centre), np.linalg.norm(thermal_centre - camera_centre)) < 80.0:
        thermal_centre[1] += 60.0
    thermal_size = _THERMAL_SIZES[rng.integers(len(_THERMAL_SIZES))]
    thermal_focal = thermal_size[0] * depth / rng.uniform(280.0, 480.0)
    thermal = _device("thermal", thermal_size, thermal_focal, _distortion(rng, (-0.2, 0.05)),
                      _aimed(thermal_centre, aim + rng.uniform(-30.0, 30.0, 3) * [1, 1, 0], rng.uniform(-5.0, 5.0)),
                      thermal_centre)

    # the part: in or out of tolerance, its shape, material, pose and temperature
    out = bool(rng.uniform() < 0.5)
    size_tolerance = float(rng.choice([0.2, 0.3, 0.5]))
    surface_tolerance = float(rng.choice([0.5, 0.8, 1.0]))
    material = str(rng.choice(["carbon-steel", "stainless-steel"]))
    defect = "none"
    # an out-of-tolerance part is off in size or has a dent or bulge (a tube, ring or box: always the latter)
    size_out = out and (kind not in ("open_tube", "ring", "box")) and rng.uniform() < 0.5
    shape = _draw_shape(kind, rng, size_out, size_tolerance)
    yaw, pitch, roll = rng.uniform(-50.0, 50.0), rng.uniform(-25.0, 25.0), rng.uniform(0.0, 360.0)
    if kind == "box":
        part_rotation = Rotation.from_euler("zyx", rng.uniform(-40.0, 40.0, 3), degrees=True).as_matrix()
    else:  # the axis (part x) turned by the yaw and pitch from across the view, rolled about itself
        part_rotation = Rotation.from_euler("xzy", [roll, pitch, yaw], degrees=True).as_matrix()
    part_centre = aim + rng.uniform(-25.0, 25.0, 3)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = part_rotation, part_centre
    core = float(rng.uniform(800.0, 1150.0))
    gradient = (rng.normal(size=3) * rng.uniform(0.0, 0.3) / np.sqrt(3)).tolist()
    spots = []
    if rng.uniform() < 0.5:
        spots.append(Spot(center=(rng.normal(size=3) * shape.radius / 2).tolist(),
                          radius=float(rng.uniform(15.0, 40.0)), amplitude=float(rng.uniform(-60.0, 40.0))))
    part_temperature = SurfaceTemperature(base=core, gradient=gradient, spots=spots)

    # fixtures and the back wall, cool
    bound = shape.radius
    wall_gap = float(rng.uniform(20.0, 200.0))
    wall_normal = Rotation.from_euler("yx", rng.uniform(-35.0, 35.0, 2), degrees=True).as_matrix() @ [0.0, 0.0, -1.0]
    wall_centre = part_centre - wall_normal * (bound + wall_gap)
    u_axis = np.cross([0.0, 1.0, 0.0], wall_normal)
    wall = Plane(center=wall_centre.tolist(), normal=wall_normal.tolist(), u_axis=(u_axis / np.linalg.norm(u_axis)).tolist(),
                 size=[1400.0, 1200.0], albedo=_texture(rng, (0.25, 0.6), (0.0, 0.2)))
    fixtures: list = []
    fixture_kinds = list(rng.choice(["support", "post_side", "post_front", "block_side"],
                                    size=int(rng.integers(1, 4)), replace=False))
    for fixture in fixture_kinds:
        albedo = _texture(rng, (0.3, 0.7), (0.0, 0.2))
        if fixture == "support":  # under the part (image y points down)
            height = float(rng.uniform(40.0, 120.0))
            centre = part_centre + [rng.uniform(-20, 20), bound + height / 2 + rng.uniform(0.0, 5.0), rng.uniform(-20, 20)]
            fixtures.append(_fixture_box(centre, (rng.uniform(60, 160), height, rng.uniform(60, 160)), albedo))
        elif fixture == "post_side":
            centre = part_centre + [rng.choice([-1, 1]) * (bound + rng.uniform(10.0, 60.0)), 0.0, rng.uniform(-40, 80)]
            fixtures.append(Cylinder(center=centre.tolist(), axis=[0.0, 1.0, 0.0], radius=float(rng.uniform(8, 30)),
                                     length=600.0, albedo=albedo))
        elif fixture == "post_front":  # between the devices and the part: hides some of it from the camera
            offset = side * (bound * rng.uniform(0.6, 1.2))
            centre = part_centre + [offset, 0.0, -(bound + rng.uniform(30.0, 120.0))]
            fixtures.append(Cylinder(center=centre.tolist(), axis=[0.0, 1.0, 0.0], radius=float(rng.uniform(5, 15)),
                                     length=600.0, albedo=albedo))
        else:
            centre = part_centre + [rng.choice([-1, 1]) * (bound + rng.uniform(20.0, 50.0)), rng.uniform(-30, 30),
                                    rng.uniform(0, 60)]
            fixtures.append(_fixture_box(centre, (rng.uniform(20, 60), rng.uniform(60, 200), rng.uniform(40, 120)),
                                         albedo))

    # the deviation on the surface: a dent or bulge (out: 2.5..4 surface tolerances; in: within 0.4)
    bumps: tuple[Bump, ...] = ()
    if out and not size_out:
        sigma = float(rng.uniform(6.0, 12.0))
        height = float(rng.uniform(2.5, 4.0) * surface_tolerance * rng.choice([-1.0, 1.0]))
        centre = _visible_bump_centre(rng, *shape.true, pose, [camera.centre, projector.centre], [*fixtures, wall], sigma)
        if centre is None:  # nothing faces both devices: make it a size deviation after all when it can be
            height = 0.0
        bumps = (Bump(center=tuple(float(c) for c in centre), sigma_mm=sigma, height_mm=height),) if height else ()
        defect = f"{'bulge' if height > 0 else 'dent'} of {abs(height):.2f} mm, sigma {sigma:.1f} mm" if height \
            else "no face seen by both devices"
    elif not out and rng.uniform() < 0.5:
        sigma = float(rng.uniform(6.0, 12.0))
        height = float(rng.uniform(-0.4, 0.4) * surface_tolerance)
        centre = shape.true[0][rng.integers(len(shape.true[0]))]
        bumps = (Bump(center=tuple(float(c) for c in centre), sigma_mm=sigma, height_mm=height),)
        defect = f"{'bulge' if height > 0 else 'dent'} of {abs(height):.2f} mm, sigma {sigma:.1f} mm (in tolerance)"
    in_tolerance = not out or (not size_out and not bumps)
    # a dent or bulge within 3 sigma of a feature's region changes what that feature measures: its true
    # value is then not the drawn one, so it is left out of the truth (and of the cold-size figures)
    values = dict(shape.true_values)
    for bump in bumps:
        for feature in shape.features:
            if "region" in feature:
                low = np.asarray(feature["region"]["min"]) - 3 * bump.sigma_mm
                high = np.asarray(feature["region"]["max"]) + 3 * bump.sigma_mm
                if np.all((np.asarray(bump.center) >= low) & (np.asarray(bump.center) <= high)):
                    values.pop(feature["name"], None)
    hot = HotPart(shape.true[0], shape.true[1], builtin_material(material), part_temperature, pose=pose, bumps=bumps)

    # temperatures: the part's field in the world; fixtures and wall warm a little
    world_part_temperature = _moved_temperature(part_temperature, pose[:3, :3], pose[:3, 3])
    wall_temperature = SurfaceTemperature(base=float(rng.uniform(25.0, 150.0)), spots=[
        Spot(center=wall_centre.tolist(), radius=float(rng.uniform(80.0, 200.0)), amplitude=float(rng.uniform(0, 100)))])
    fixture_temperatures = [SurfaceTemperature(base=float(rng.uniform(30.0, 250.0))) for _ in fixtures]

    light = "white" if rng.uniform() < 0.25 else "blue"
    optics = hot_optics("white") if light == "white" else hot_optics("blue", (450.0, 40.0))
    camera_effects = CameraEffects(blur_sigma=float(rng.uniform(0.3, 1.0)), noise_sigma=1.0)
    projector_effects = ProjectorEffects(blur_sigma=float(rng.uniform(0.3, 1.0)))
    thermal_effects = ThermalEffects(supersample=3, blur_sigma=float(rng.uniform(0.4, 1.0)),
                                     netd=float(rng.uniform(0.05, 0.3)))
    part_albedo = Albedo(base=1 - HOT_STEEL_EMISSIVITY, texture_amplitude=float(rng.uniform(0.0, 0.04)),
                         feature_size=float(rng.uniform(15.0, 40.0)), seed=int(rng.integers(0, 2**31)))

    # a random world frame: every pose, surface and field moved by one rigid motion
    world_rotation = Rotation.random(random_state=rng).as_matrix()
    world_translation = rng.uniform(-1000.0, 1000.0, 3)
    surfaces = [hot.surface().model_copy(update={"albedo": part_albedo}), *fixtures, wall]
    surfaces = [_moved(surface, world_rotation, world_translation) for surface in surfaces]
    motion = np.eye(4)
    motion[:3, :3], motion[:3, 3] = world_rotation, world_translation
    hot = HotPart(hot.vertices, hot.triangles, hot.material, hot.temperature, pose=motion @ pose, bumps=bumps)
    temperatures = TemperatureScene(background=25.0, surfaces=[
        _moved_temperature(t, world_rotation, world_translation)
        for t in [world_part_temperature, *fixture_temperatures, wall_temperature]])
    scene = Scene(surfaces=surfaces, ambient=0.01, temperature=temperatures, optics=optics)
    rig = Rig(devices={name: _moved_device(device, world_rotation, world_translation)
                       for name, device in (("projector", projector), ("camera", camera), ("thermal", thermal))})

    part_file = {"version": 1, "name": f"zoo-{seed}-{kind}", "material": material, "nominal": "nominal.stl",
                 "features": shape.features, "surface_tolerance": [-surface_tolerance, surface_tolerance]}
    description = {
        "kind": kind, "shape": shape.deviation, "defect": defect, "material": material, "core_c": round(core, 1),
        "light": light, "projector": f"{projector_size[0]}x{projector_size[1]} f {projector_focal:.0f}",
        "camera": f"{camera_size[0]}x{camera_size[1]} f {camera_focal:.0f}",
        "thermal": f"{thermal_size[0]}x{thermal_size[1]} f {thermal_focal:.0f}",
        "baseline_mm": round(baseline, 1), "depth_mm": round(depth, 1), "fixtures": fixture_kinds,
        "wall_gap_mm": round(wall_gap, 1), "size_tolerance": size_tolerance, "surface_tolerance": surface_tolerance}
    return ZooScene(seed=seed, kind=kind, rig=rig, scene=scene, temperatures=temperatures, part=hot,
                    nominal_vertices=shape.nominal[0], nominal_triangles=shape.nominal[1], part_file=part_file,
                    truth=ZooTruth(in_tolerance=in_tolerance, features={k: float(v) for k, v in values.items()},
                                   deviation=f"{shape.deviation}; {defect}"),
                    camera_effects=camera_effects, projector_effects=projector_effects,
                    thermal_effects=thermal_effects, projector_light=light, description=description)
