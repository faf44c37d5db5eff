"""A small simulated hot scene with known temperatures: a hot plate behind a hotter bar that hides part of it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from services.formats.rig import Device
from services.geometry.camera import pixel_grid, pixel_rays
from services.simulation.raycast import cast_rays
from services.simulation.scene import Cylinder, Plane, Scene
from services.simulation.thermal import (
    Spot, SurfaceTemperature, TemperatureScene, ThermalEffects, render_thermal, seen_by, surface_temperature,
)


def look_at(kind: str, centre, target, focal: float, width: int, height: int, dist=()) -> Device:
    """A device at ``centre`` whose optical axis points at ``target`` (y roughly down)."""
    centre = np.asarray(centre, dtype=float)
    forward = np.asarray(target, dtype=float) - centre
    forward /= np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])
    K = [[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]]
    return Device(kind=kind, width=width, height=height, K=K, dist=list(dist), R=R.tolist(),
                  t=(-R @ centre).tolist())


@dataclass
class HotScene:
    scene: Scene
    temperatures: TemperatureScene
    camera: Device
    thermal: Device
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
    origin, directions = pixel_rays(pixel_grid(camera.width, camera.height), camera.K_array, camera.dist_array,
                                    camera.R_array, camera.t_array)
    hits = cast_rays(scene, origin, directions)
    hit = hits.surface >= 0
    points, normals = hits.points[hit], hits.normals[hit]
    image = render_thermal(scene, temperatures, thermal, ThermalEffects(supersample=3), np.random.default_rng(seed))
    return HotScene(scene, temperatures, camera, thermal, points, normals,
                    surface_temperature(temperatures, points, hits.surface[hit]),
                    seen_by(scene, thermal, points), image)


def rerender(hot: HotScene, seed: int) -> np.ndarray:
    """Another thermal frame of the same scene with different noise."""
    return render_thermal(hot.scene, hot.temperatures, hot.thermal, ThermalEffects(supersample=3),
                          np.random.default_rng(seed))


@pytest.fixture(scope="session")
def hot_scene() -> HotScene:
    return make_hot_scene()
