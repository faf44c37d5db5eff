"""The simulated thermal camera: temperature fields on scene surfaces and the camera's view of them.

A ``TemperatureScene`` gives each surface of a ``Scene`` (same order) a smooth
temperature field, in degrees Celsius,

    T(X) = base + g . (X - origin) + sum_k a_k exp(-|X - c_k|^2 / (2 r_k^2)),

a linear gradient plus Gaussian hot (a_k > 0) or cold (a_k < 0) spots. Rays that
miss every surface see ``background``.
"""

from __future__ import annotations

from typing import Annotated

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from services.formats.rig import Device
from services.fusion.radiometry import PlanckConstants, blackbody_counts, blackbody_temperature
from services.geometry.camera import camera_center
from services.simulation.raycast import cast_rays
from services.simulation.render import integrate_pixels, subsample_rays
from services.simulation.scene import Scene

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class Spot(BaseModel):
    """A Gaussian hot or cold spot: ``amplitude`` kelvin at ``center``, standard deviation ``radius`` mm."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    center: Vector3
    radius: float = Field(gt=0)
    amplitude: float


class SurfaceTemperature(BaseModel):
    """A smooth temperature field on one surface, degrees Celsius."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    base: float = Field(gt=-273.15)
    gradient: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    origin: Vector3 = Field(default_factory=lambda: [0.0, 0.0, 0.0])
    spots: list[Spot] = Field(default_factory=list)

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """Temperature at world points (N, 3) -> (N,)."""
        points = np.asarray(points, dtype=np.float64)
        temperature = self.base + (points - np.asarray(self.origin)) @ np.asarray(self.gradient)
        for spot in self.spots:
            squared = np.sum((points - np.asarray(spot.center)) ** 2, axis=1)
            temperature = temperature + spot.amplitude * np.exp(-squared / (2 * spot.radius**2))
        return temperature


class TemperatureScene(BaseModel):
    """One temperature field per scene surface (same order), and what rays that miss see."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    surfaces: list[SurfaceTemperature] = Field(min_length=1)
    background: float = Field(25.0, gt=-273.15)


class ThermalEffects(BaseModel):
    """The thermal camera's imperfections.

    ``supersample`` x ``supersample`` rays per pixel (an odd number) integrate its area;
    ``blur_sigma`` is the optics' Gaussian blur in pixels; ``netd`` the noise
    equivalent temperature difference in kelvin (Gaussian noise of that standard
    deviation at every temperature). Area integration and blur act on radiance
    (counts on ``planck``'s curve), not on temperature, as in a real camera.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    supersample: int = Field(3, ge=1, le=7)
    blur_sigma: float = Field(0.6, ge=0.0)
    netd: float = Field(0.05, ge=0.0)
    planck: PlanckConstants = Field(default_factory=PlanckConstants)


def surface_temperature(temperatures: TemperatureScene, points: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """True temperature of points (N, 3) on scene surfaces ``surface`` (N,); ``background`` where -1."""
    result = np.full(len(points), temperatures.background, dtype=np.float64)
    for index, field in enumerate(temperatures.surfaces):
        on_surface = surface == index
        if on_surface.any():
            result[on_surface] = field.evaluate(points[on_surface])
    return result


def render_thermal(
    scene: Scene,
    temperatures: TemperatureScene,
    device: Device,
    effects: ThermalEffects,
    rng: np.random.Generator,
) -> np.ndarray:
    """What a calibrated thermal camera reads of a scene, degrees Celsius.

    Parameters
    ----------
    scene : Scene
        The geometry.
    temperatures : TemperatureScene
        One field per surface of ``scene``.
    device : Device
        The thermal camera (intrinsics, distortion and pose).
    effects : ThermalEffects
        Area integration, blur and noise.
    rng : numpy.random.Generator
        Source of the noise.

    Returns
    -------
    image : (height, width) float32 array
        Temperature per pixel.

    Notes
    -----
    Each pixel's value is P^-1( G_sigma * mean_s P(T(X_s)) ) + n with X_s the
    scene point hit by the s-th sub-pixel ray (through the lens distortion), P
    the camera's Planck curve, G_sigma the optics' blur and n ~ N(0, NETD^2).
    """
    if len(temperatures.surfaces) != len(scene.surfaces):
        raise ValueError(
            f"The temperature scene has {len(temperatures.surfaces)} surface fields but the scene has "
            f"{len(scene.surfaces)} surfaces; give one per surface."
        )
    origin, directions = subsample_rays(device, effects.supersample)
    hits = cast_rays(scene, origin, directions)
    temperature = surface_temperature(temperatures, hits.points, hits.surface)
    samples = blackbody_counts(temperature, effects.planck).reshape(device.height * effects.supersample, -1)
    counts = integrate_pixels(samples, effects.supersample)
    if effects.blur_sigma > 0:
        counts = cv2.GaussianBlur(counts, (0, 0), effects.blur_sigma, borderType=cv2.BORDER_REPLICATE)
    image = blackbody_temperature(counts, effects.planck)
    image = image + rng.normal(0.0, effects.netd, image.shape)
    return image.astype(np.float32)


def seen_by(scene: Scene, device: Device, points: np.ndarray, tolerance_mm: float = 0.5) -> np.ndarray:
    """Ground truth visibility: whether the device's line of sight to each point (N, 3) is unobstructed.

    A point is seen when the first scene hit along the ray from the device
    centre toward it is no nearer than the point itself, less ``tolerance_mm``.
    Pixel bounds are not checked.
    """
    points = np.asarray(points, dtype=np.float64)
    centre = camera_center(device.R_array, device.t_array)
    toward = points - centre
    distance = np.linalg.norm(toward, axis=1)
    hits = cast_rays(scene, centre, toward)
    return hits.distance >= distance - tolerance_mm


def forging_temperatures() -> TemperatureScene:
    """The temperature field of ``presets.forging_scene()`` (surfaces billet, flange, back wall), degrees C.

    Billet: 1040 C at its centre, rising 0.2 K/mm toward +x (the end last out of the furnace), a
    +45 K hot spot (sigma 30 mm) on its front and a -80 K spot (sigma 25 mm) where it was gripped,
    so 950-1090 C. Flange: thinner, cooler, 960 C falling 0.4 K/mm toward its top (y < 0). Back wall:
    45 C warmed to 120 C (sigma 150 mm) behind the part. Misses see 25 C.
    """
    return TemperatureScene(background=25.0, surfaces=[
        SurfaceTemperature(base=1040.0, gradient=[0.2, 0.0, 0.0], origin=[0.0, 20.0, 600.0], spots=[
            Spot(center=[30.0, 10.0, 545.0], radius=30.0, amplitude=45.0),
            Spot(center=[-60.0, -30.0, 580.0], radius=25.0, amplitude=-80.0),
        ]),
        SurfaceTemperature(base=960.0, gradient=[0.0, 0.4, 0.0], origin=[-95.0, 20.0, 600.0]),
        SurfaceTemperature(base=45.0, spots=[Spot(center=[0.0, 20.0, 760.0], radius=150.0, amplitude=75.0)]),
    ])
