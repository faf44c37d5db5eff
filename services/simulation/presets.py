"""Ready-made rigs and scenes: the paper's simulated experiment and the forging station of later issues.

Paper rig (section 2.1 and 3 of the paper): projector "projector" at the world origin (R = I, t = 0) and
camera "camera" centred at (400, 0, 0) mm, rotated 20.0 degrees about y (the exactly orthonormal form
of the paper's Table 1 rotation [[0.94, 0, 0.342], [0, 1, 0], [-0.342, 0, 0.94]]) so that its optical
axis (-0.342, 0, 0.940) turns toward the projector's; both 1024x768 with principal points at the image
centres and no distortion; focal lengths 1300 px (projector) and 800 px (camera).

Gray-code scanner rig (a foreign scanner coding Gray code alone): projector "projector" 1824x1140,
f = 2500 px, at the origin looking along +z; camera "camera" 1280x1024, f = 1800 px, centred at
(250, 0, 0) and aimed at (0, 0, 500); no distortion. ``scale`` divides every size and focal length.

Forging rig: projector "projector" 1280x800, f = 1500 px, at the origin looking along +z; camera
"camera" 1280x800, f = 1400 px, centred at (350, 0, 0); thermal camera "thermal" 320x256, f = 380 px,
centred at (180, -120, 0) (above the projector, y pointing down). Camera and thermal camera aim at
(0, 0, 600). All three have mild radial and tangential distortion.
"""

from __future__ import annotations

import numpy as np

from services.formats.rig import Head, Rig
from services.geometry.camera_model import CameraModel
from services.simulation.optics import BandPassFilter, Optics, ProjectorOptics
from services.simulation.scene import Albedo, Cylinder, Plane, Scene, Sphere
from services.simulation.temperature import Spot, SurfaceTemperature, TemperatureScene

PAPER_SIZE = (1024, 768)
PAPER_PROJECTOR_FOCAL = 1300.0
PAPER_CAMERA_FOCAL = 800.0
PAPER_CAMERA_CENTRE = (400.0, 0.0, 0.0)
PAPER_CAMERA_ROTATION_DEG = 20.0
PAPER_SPHERE_CENTRE = (0.0, 0.0, 480.0)
FORGING_AIM = (0.0, 0.0, 600.0)


def _intrinsics(focal: float, width: int, height: int) -> list[list[float]]:
    return [[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]]


def _device(kind: str, size: tuple[int, int], focal: float, dist: list[float], R: np.ndarray,
            centre: tuple[float, float, float]) -> CameraModel:
    t = -R @ np.asarray(centre, dtype=np.float64)
    return CameraModel(kind=kind, width=size[0], height=size[1], K=_intrinsics(focal, *size), dist=dist,
                  R=R.tolist(), t=t.tolist())


def _rotation_about_y(degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def look_at_rotation(centre: tuple[float, float, float], target: tuple[float, float, float]) -> np.ndarray:
    """Rotation aiming the device z axis from ``centre`` at ``target``, its x axis level (normal to world y)."""
    forward = np.subtract(target, centre, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def paper_rig() -> Rig:
    """The paper's simulated structured-light rig (numbers in the module docstring)."""
    return Rig(devices={
        "projector": _device("projector", PAPER_SIZE, PAPER_PROJECTOR_FOCAL, [], np.eye(3), (0.0, 0.0, 0.0)),
        "camera": _device("camera", PAPER_SIZE, PAPER_CAMERA_FOCAL, [],
                          _rotation_about_y(PAPER_CAMERA_ROTATION_DEG), PAPER_CAMERA_CENTRE),
    })


def paper_plane(depth_mm: float, albedo: Albedo = Albedo()) -> Scene:
    """The paper's 300 x 200 mm plane facing the projector (normal -z), centred at (0, 0, depth_mm)."""
    return Scene(surfaces=[Plane(center=[0.0, 0.0, depth_mm], normal=[0.0, 0.0, -1.0], u_axis=[1.0, 0.0, 0.0],
                                 size=[300.0, 200.0], albedo=albedo)])


def paper_sphere(radius_mm: float, albedo: Albedo = Albedo()) -> Scene:
    """The paper's sphere of radius ``radius_mm`` centred at (0, 0, 480) mm."""
    return Scene(surfaces=[Sphere(center=list(PAPER_SPHERE_CENTRE), radius=radius_mm, albedo=albedo)])


def gray_scanner_rig(scale: int = 1) -> Rig:
    """The Gray-code scanner rig, every size and focal length divided by ``scale`` (module docstring)."""
    if scale < 1 or 1824 % scale or 1140 % scale or 1280 % scale or 1024 % scale:
        raise ValueError(f"scale must be a positive common divisor of 1824, 1140, 1280 and 1024; got {scale}.")
    camera_centre = (250.0, 0.0, 0.0)
    return Rig(devices={
        "projector": _device("projector", (1824 // scale, 1140 // scale), 2500.0 / scale, [], np.eye(3),
                             (0.0, 0.0, 0.0)),
        "camera": _device("camera", (1280 // scale, 1024 // scale), 1800.0 / scale, [],
                          look_at_rotation(camera_centre, (0.0, 0.0, 500.0)), camera_centre),
    })


def forging_rig(scale: float = 1.0) -> Rig:
    """The forging station: projector, visible camera and thermal camera (numbers in the module docstring).

    ``scale`` shrinks the projector's and the camera's images and focal lengths alike (the same view
    at a lower resolution, for fast tests); the thermal camera keeps its own.
    """
    def size(width: int, height: int) -> tuple[int, int]:
        return round(width * scale), round(height * scale)

    return Rig(devices={
        "projector": _device("projector", size(1280, 800), 1500.0 * scale, [0.02, -0.01, 0.0, 0.0, 0.0],
                             np.eye(3), (0.0, 0.0, 0.0)),
        "camera": _device("camera", size(1280, 800), 1400.0 * scale, [-0.08, 0.12, 0.0005, -0.0003, -0.02],
                          look_at_rotation((350.0, 0.0, 0.0), FORGING_AIM), (350.0, 0.0, 0.0)),
        "thermal": _device("thermal", (320, 256), 380.0, [-0.15, 0.08, 0.001, 0.0005, 0.0],
                           look_at_rotation((180.0, -120.0, 0.0), FORGING_AIM), (180.0, -120.0, 0.0)),
    })


def forging_scene() -> Scene:
    """A hot forged part at about 600 mm: a capped billet lying along x with a flange, before a back wall.

    Surfaces (index: shape): 0: billet, cylinder radius 55 mm, length 220 mm, axis x, centre (0, 20, 600);
    1: flange, cylinder radius 80 mm, length 24 mm, coaxial, centre (-95, 20, 600); 2: back wall, plane
    700 x 500 mm at z = 760 facing the devices. The thermal camera looks from above, so parts of the wall
    below the billet and of the billet's underside that the camera and projector see are hidden from it.
    """
    steel = Albedo(base=0.55, texture_amplitude=0.15, feature_size=25.0, seed=1)
    return Scene(ambient=0.05, surfaces=[
        Cylinder(center=[0.0, 20.0, 600.0], axis=[1.0, 0.0, 0.0], radius=55.0, length=220.0, albedo=steel),
        Cylinder(center=[-95.0, 20.0, 600.0], axis=[1.0, 0.0, 0.0], radius=80.0, length=24.0, albedo=steel),
        Plane(center=[0.0, 0.0, 760.0], normal=[0.0, 0.0, -1.0], u_axis=[1.0, 0.0, 0.0], size=[700.0, 500.0],
              albedo=Albedo(base=0.4, texture_amplitude=0.1, feature_size=40.0, seed=2)),
    ])


# Oxidised steel is opaque and nearly grey: emissivity 0.85 and, by Kirchhoff's law, albedo 0.15.
HOT_STEEL_EMISSIVITY = 0.85
_HOT_PROJECTORS = {
    "white": ProjectorOptics(spectrum="white_led", radiant_power_w=20.0),
    "blue": ProjectorOptics(spectrum="blue_led", centre_nm=450.0, fwhm_nm=20.0, radiant_power_w=30.0),
}


def hot_optics(projector: str = "white", band_pass: tuple[float, float] | None = None) -> Optics:
    """The hot-part station's optics: a 20 W white LED or 30 W blue (450 nm) LED projector over the
    rig's 0.164 m^2 at 600 mm, a 12-bit mono CMOS camera, optionally a band-pass filter (centre, FWHM nm)."""
    if projector not in _HOT_PROJECTORS:
        raise ValueError(f"The hot-part projector is 'white' or 'blue'; got {projector!r}.")
    camera_filter = None if band_pass is None else BandPassFilter(centre_nm=band_pass[0], fwhm_nm=band_pass[1])
    return Optics(projector=_HOT_PROJECTORS[projector], camera_filter=camera_filter,
                  emissivity=HOT_STEEL_EMISSIVITY)


def hot_part_scene(peak_c: float, optics: Optics | None = None, cooling_rate: float = 0.0) -> Scene:
    """A glowing billet and dome before a cool fixture plate, for the forging rig (docs/hot-parts.md).

    Surfaces (index: shape): 0: billet, capped cylinder radius 45 mm, length 150 mm along x, centre
    (-70, 0, 620), at ``peak_c`` - 60 K with a +60 K spot (sigma 60 mm) on its front; 1: dome, sphere of
    radius 80 mm centred (100, 0, 700) on the plate, at ``peak_c`` - 90 K with a +70 K spot on its top;
    2: fixture plate 600 x 400 mm at z = 700 facing the devices, 40 C. Part albedo 0.15 +- 0.03 (oxidised
    steel, 1 - emissivity), plate 0.4 +- 0.1; ambient 0.01. The parts cool at ``cooling_rate`` K/s.
    """
    scale = Albedo(base=1 - HOT_STEEL_EMISSIVITY, texture_amplitude=0.03, feature_size=25.0, seed=1)
    temperature = TemperatureScene(background=25.0, surfaces=[
        SurfaceTemperature(base=peak_c - 60.0, cooling_rate=cooling_rate,
                           spots=[Spot(center=[-70.0, 0.0, 575.0], radius=60.0, amplitude=60.0)]),
        SurfaceTemperature(base=peak_c - 90.0, cooling_rate=cooling_rate,
                           spots=[Spot(center=[100.0, 0.0, 620.0], radius=60.0, amplitude=70.0)]),
        SurfaceTemperature(base=40.0),
    ])
    return Scene(ambient=0.01, temperature=temperature, optics=optics or hot_optics(), surfaces=[
        Cylinder(center=[-70.0, 0.0, 620.0], axis=[1.0, 0.0, 0.0], radius=45.0, length=150.0, albedo=scale),
        Sphere(center=[100.0, 0.0, 700.0], radius=80.0, albedo=scale),
        Plane(center=[0.0, 0.0, 700.0], normal=[0.0, 0.0, -1.0], u_axis=[1.0, 0.0, 0.0], size=[600.0, 400.0],
              albedo=Albedo(base=0.4, texture_amplitude=0.1, feature_size=40.0, seed=2)),
    ])


SHADOW_AIM = (0.0, 0.0, 650.0)
SHADOW_BASELINE_MM = 260.0


def shadow_rig(scale: float = 1.0) -> Rig:
    """Projector 1024x768 (f 1150 px) at the origin, camera 1280x800 (f 1400 px, mild distortion) 260 mm to its
    side, both aimed at (0, 0, 650); ``scale`` shrinks both images and focal lengths alike."""
    def device(kind, width, height, focal, dist, centre):
        w, h = round(width * scale), round(height * scale)
        R = look_at_rotation(centre, SHADOW_AIM)
        K = [[focal * scale, 0.0, (w - 1) / 2], [0.0, focal * scale, (h - 1) / 2], [0.0, 0.0, 1.0]]
        return CameraModel(kind=kind, width=w, height=h, K=K, dist=dist, R=R.tolist(),
                           t=(-R @ np.asarray(centre, np.float64)).tolist())

    return Rig(devices={
        "projector": device("projector", 1024, 768, 1150.0, [], (0.0, 0.0, 0.0)),
        "camera": device("camera", 1280, 800, 1400.0, [-0.06, 0.09, 0.0004, -0.0002, 0.0],
                         (SHADOW_BASELINE_MM, 0.0, 0.0)),
    })


def shadow_scene(peak_c: float | None = None, projector: str = "white",
                 band_pass: tuple[float, float] | None = None) -> Scene:
    """A capped cylinder (r 40 mm, 160 mm long, vertical) and a sphere (r 60 mm) before a plate tilted 25 degrees
    about the vertical, 720..800 mm away, under room light (ambient 0.1): the parts cast projector shadows on
    the plate that the camera sees, and the shadows are not dark. Surfaces: 0 cylinder, 1 sphere, 2 plate.
    Glowing at ``peak_c`` (C, the cylinder 60 K and the sphere 80 K cooler away from their hot spots; the
    plate 40 C) under ``hot_optics(projector, band_pass)`` when given. Issue 34's tuning scene."""
    hot = peak_c is not None
    part = Albedo(base=1 - HOT_STEEL_EMISSIVITY if hot else 0.5, texture_amplitude=0.03 if hot else 0.12,
                  feature_size=25.0, seed=3)
    tilt = np.radians(25.0)
    normal = [-np.sin(tilt), 0.0, -np.cos(tilt)]
    u_axis = [np.cos(tilt), 0.0, -np.sin(tilt)]
    surfaces = [
        Cylinder(center=[-75.0, 0.0, 600.0], axis=[0.0, 1.0, 0.0], radius=40.0, length=160.0, albedo=part),
        Sphere(center=[85.0, 10.0, 640.0], radius=60.0, albedo=part),
        Plane(center=[0.0, 0.0, 760.0], normal=normal, u_axis=u_axis, size=[700.0, 500.0],
              albedo=Albedo(base=0.45, texture_amplitude=0.12, feature_size=35.0, seed=4)),
    ]
    if not hot:
        return Scene(ambient=0.1, surfaces=surfaces)  # room light: the shadows are not dark
    temperature = TemperatureScene(background=25.0, surfaces=[
        SurfaceTemperature(base=peak_c - 60.0,
                           spots=[Spot(center=[-75.0, 0.0, 560.0], radius=60.0, amplitude=60.0)]),
        SurfaceTemperature(base=peak_c - 80.0,
                           spots=[Spot(center=[85.0, 10.0, 580.0], radius=60.0, amplitude=80.0)]),
        SurfaceTemperature(base=40.0),
    ])
    return Scene(ambient=0.1, temperature=temperature, optics=hot_optics(projector, band_pass), surfaces=surfaces)


STATION_SHAFT_RADIUS_MM = 45.0
STATION_SHAFT_LENGTH_MM = 300.0
STATION_HEAD_DISTANCE_MM = 450.0
STATION_HEAD_OFFSET_MM = 350.0
STATION_BASELINE_MM = 150.0
STATION_THERMAL_DISTANCE_MM = 550.0
_STATION_DISTORTION = [-0.08, 0.12, 0.0005, -0.0003, -0.02]
_STATION_THERMAL_DISTORTION = [-0.15, 0.08, 0.001, 0.0005, 0.0]


def _axis_aligned_rotation(centre: np.ndarray, target: np.ndarray, along: np.ndarray) -> np.ndarray:
    """Rotation aiming the device z axis from ``centre`` at ``target``, its x axis as near ``along`` as it can be."""
    forward = np.subtract(target, centre, dtype=np.float64)
    forward /= np.linalg.norm(forward)
    right = along - np.dot(along, forward) * forward
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def station_head_meridian(index: int, heads: int) -> np.ndarray:
    """The unit direction (world, in the y-z plane) from the shaft's axis toward head ``index`` of ``heads``: the
    first head straight above the shaft (-y, world y points down), the others evenly around it."""
    angle = -np.pi / 2 + 2 * np.pi * index / heads
    return np.array([0.0, np.sin(angle), np.cos(angle)])


def station_rig(scale: float = 1.0, heads: int = 4) -> Rig:
    """A station of ``heads`` sensor heads around a horizontal shaft (world x along its axis, centred at the
    origin, y down), and two thermal cameras: a version-2 rig whose heads are ``head-1`` ... ``head-N``.

    Head k (camera ``camera-k``, projector ``projector-k``, each 1280x800 with mild distortion, focal
    lengths 1200 and 1260 px) lies 450 mm from the axis on its meridian (the first straight above), its
    camera and projector 150 mm apart across the meridian (the coded projector axis is y, the images' long
    side along the shaft), both aimed at the shaft's centre. The heads are offset 350 mm along the axis,
    odd heads toward +x, even heads toward -x, so that every end face is seen by two opposite heads at
    about 66 degrees from its normal (a head straight over the shaft would see neither end face, which the
    length between them needs); every point of the shaft's side then faces some head (camera and
    projector) within 50 degrees at the median and 65 at the 95th percentile. Neighbouring heads overlap on the lateral surface between their meridians,
    opposite heads on their end face: the overlaps the merge registers the heads on.

    Thermal cameras ``thermal-1`` and ``thermal-2`` (320x256, f 380 px) lie 550 mm from the axis halfway
    between the first two heads' meridians and opposite, aimed at the centre: each sees about 150 degrees
    of the circumference along the whole length. ``scale`` shrinks the cameras' and projectors' images and
    focal lengths alike (the thermal cameras keep theirs), for fast tests.
    """
    if heads < 2:
        raise ValueError(f"A station has at least two heads; got {heads}.")

    def size(width: int, height: int) -> tuple[int, int]:
        return round(width * scale), round(height * scale)

    devices: dict[str, CameraModel] = {}
    station_heads = []
    axis = np.array([1.0, 0.0, 0.0])
    for index in range(heads):
        radial = station_head_meridian(index, heads)
        across = np.cross(axis, radial)
        centre = STATION_HEAD_DISTANCE_MM * radial + (1 if index % 2 == 0 else -1) * STATION_HEAD_OFFSET_MM * axis
        name = f"{index + 1}"
        for kind, side, focal in (("projector", -0.5, 1260.0), ("camera", 0.5, 1200.0)):
            position = centre + side * STATION_BASELINE_MM * across
            devices[f"{kind}-{name}"] = _device(kind, size(1280, 800), focal * scale, _STATION_DISTORTION,
                                                _axis_aligned_rotation(position, np.zeros(3), axis),
                                                tuple(position))
        station_heads.append(Head(f"head-{name}", f"camera-{name}", f"projector-{name}"))
    for number, angle in ((1, np.pi / heads), (2, np.pi / heads + np.pi)):
        radial = np.array([0.0, np.sin(-np.pi / 2 + angle), np.cos(-np.pi / 2 + angle)])
        position = STATION_THERMAL_DISTANCE_MM * radial
        devices[f"thermal-{number}"] = _device("thermal", (320, 256), 380.0, _STATION_THERMAL_DISTORTION,
                                               _axis_aligned_rotation(position, np.zeros(3), axis), tuple(position))
    return Rig(devices=devices, station_heads=tuple(station_heads))
