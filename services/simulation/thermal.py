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
from services.geometry.camera import camera_center, pixel_grid, pixel_rays
from services.simulation.raycast import cast_rays
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

    ``supersample`` x ``supersample`` rays per pixel integrate its area;
    ``blur_sigma`` is the optics' Gaussian blur in pixels; ``netd`` the noise
    equivalent temperature difference in kelvin (Gaussian noise of that standard
    deviation at every temperature). Area integration and blur act on radiance
    (counts on ``planck``'s curve), not on temperature, as in a real camera.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, arbitrary_types_allowed=True)

    supersample: int = Field(3, ge=1, le=8)
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
    samples = effects.supersample
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    grid = pixel_grid(device.width, device.height)
    sub_u, sub_v = np.meshgrid(offsets, offsets)
    subpixels = (grid[:, None, :] + np.column_stack([sub_u.ravel(), sub_v.ravel()])[None]).reshape(-1, 2)
    origin, directions = pixel_rays(subpixels, device.K_array, device.dist_array, device.R_array, device.t_array)
    hits = cast_rays(scene, origin, directions)
    temperature = surface_temperature(temperatures, hits.points, hits.surface)
    counts = blackbody_counts(temperature, effects.planck).reshape(device.height, device.width, -1).mean(axis=2)
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
