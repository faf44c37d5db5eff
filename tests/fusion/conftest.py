"""Simulated hot scenes with known temperatures for the fusion tests.

``hot_scene``: a hot plate behind a hotter bar that hides part of it, with the exact cloud.
``forging_capture``: the forging station (presets) as files: rig, structured-light capture and thermal frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from services.formats.images import write_png
from services.formats.rig import Rig, save_rig
from services.geometry.camera_model import CameraModel
from services.formats.sequence import save_sequence
from services.formats.thermal import write_thermal_frame
from services.geometry.camera import pixel_grid, pixel_rays
from services.simulation.presets import forging_rig, forging_scene, look_at_rotation
from services.simulation.raycast import cast_rays
from services.simulation.render import CameraEffects, GroundTruth, render_frames, render_view
from services.simulation.scene import Cylinder, Plane, Scene
from services.simulation.thermal import (
    Spot, SurfaceTemperature, TemperatureScene, ThermalEffects, forging_temperatures, render_thermal, seen_by,
    surface_temperature,
)
from services.structured_light.patterns import generate_sequence

# The forging rig's camera and projector are simulated at half their 1280x800 resolution to keep
# the tests fast; the thermal camera keeps its 320x256 (experiments/field_accuracy.py runs full size).
_FORGING_SCALE = 2


def look_at(kind: str, centre, target, focal: float, width: int, height: int, dist=()) -> CameraModel:
    """A device at ``centre`` whose optical axis points at ``target`` (y roughly down)."""
    centre = np.asarray(centre, dtype=float)
    R = look_at_rotation(centre, target)
    K = [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]]
    return CameraModel(kind=kind, width=width, height=height, K=K, dist=list(dist), R=R.tolist(),
                  t=(-R @ centre).tolist())


@dataclass
class HotScene:
    scene: Scene
    temperatures: TemperatureScene
    camera: CameraModel
    thermal: CameraModel
    points: np.ndarray
    normals: np.ndarray
    truth: np.ndarray
    visible: np.ndarray
    image: np.ndarray


def make_hot_scene(seed: int = 0) -> HotScene:
    scene = Scene(surfaces=[
        Plane(center=[0, 0, 650], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[500, 400]),
        Cylinder(center=[0, 0, 560], axis=[1, 0, 0], radius=40, length=200),
    ])
    temperatures = TemperatureScene(surfaces=[
        SurfaceTemperature(base=800, gradient=[0.5, 0.2, 0], spots=[Spot(center=[50, 50, 650], radius=40,
                                                                         amplitude=250)]),
        SurfaceTemperature(base=1000, gradient=[0, -1, 0], origin=[0, 0, 560]),
    ])
    camera = look_at("camera", [350, 0, 0], [0, 0, 600], 700, 640, 400)
    thermal = look_at("thermal", [180, -120, 0], [0, 0, 600], 380, 320, 256, dist=[-0.1, 0.05, 0, 0, 0])
    origin, directions = pixel_rays(pixel_grid(camera.width, camera.height), camera.K, camera.dist,
                                    camera.R, camera.t)
    hits = cast_rays(scene, origin, directions)
    hit = hits.surface >= 0
    points, normals = hits.points[hit], hits.normals[hit]
    image = render_thermal(scene, temperatures, thermal, ThermalEffects(supersample=3), np.random.default_rng(seed))
    return HotScene(scene, temperatures, camera, thermal, points, normals,
                    surface_temperature(temperatures, points, hits.surface[hit]),
                    seen_by(scene, thermal, points), image)


def noiseless_image(hot: HotScene) -> np.ndarray:
    """The thermal frame of the same scene without noise."""
    return render_thermal(hot.scene, hot.temperatures, hot.thermal, ThermalEffects(supersample=3, netd=0.0),
                          np.random.default_rng(0))


@pytest.fixture(scope="session")
def hot_scene() -> HotScene:
    return make_hot_scene()


def _downscaled(device: CameraModel, factor: int) -> CameraModel:
    """The same device with ``factor`` times fewer pixels per side (distortion is in normalised units)."""
    K = device.K.copy()
    K[:2, :2] /= factor
    K[:2, 2] = (K[:2, 2] + 0.5) / factor - 0.5
    return device.replace(**{"width": device.width // factor, "height": device.height // factor,
                                     "K": K.tolist()})


@dataclass
class ForgingCapture:
    rig_path: Path
    captures: Path
    thermal_path: Path
    rig: Rig
    truth: GroundTruth
    seen_by_thermal: np.ndarray
    true_temperature: np.ndarray


@pytest.fixture(scope="session")
def forging_capture(tmp_path_factory) -> ForgingCapture:
    directory = tmp_path_factory.mktemp("forging")
    full = forging_rig()
    rig = Rig(devices={name: device if device.kind == "thermal" else _downscaled(device, _FORGING_SCALE)
                       for name, device in full.devices.items()})
    scene, temperatures = forging_scene(), forging_temperatures()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    rng = np.random.default_rng(7)
    sequence, patterns = generate_sequence(projector.width, projector.height, period=8)
    view = render_view(scene, camera, projector, supersample=1)
    frames = render_frames(view, patterns, rng, CameraEffects(noise_sigma=1.0))
    captures = directory / "capture"
    captures.mkdir()
    for frame, image in zip(sequence.frames, frames):
        write_png(captures / frame.file, image)
    save_sequence(sequence, captures)
    save_rig(rig, directory / "rig.json")
    write_thermal_frame(directory / "thermal.tif",
                        render_thermal(scene, temperatures, thermal, ThermalEffects(netd=0.05), rng))
    truth = view.truth
    on_surface = truth.surface >= 0
    seen = np.zeros(truth.surface.shape, dtype=bool)
    seen[on_surface] = seen_by(scene, thermal, truth.points[on_surface])
    true_temperature = np.full(truth.surface.shape, np.nan)
    true_temperature[on_surface] = surface_temperature(temperatures, truth.points[on_surface],
                                                       truth.surface[on_surface])
    return ForgingCapture(directory / "rig.json", captures, directory / "thermal.tif", rig, truth, seen,
                          true_temperature)
