"""The simulated thermal camera: its view of the temperature fields on scene surfaces.

The fields themselves (``TemperatureScene``, ``SurfaceTemperature``, ``Spot``, ``surface_temperature``)
live in ``services.simulation.temperature`` and are re-exported here.
"""

from __future__ import annotations

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from services.geometry.camera_model import CameraModel
from services.fusion.radiometry import PlanckConstants, blackbody_counts, blackbody_temperature

from services.simulation.raycast import cast_rays
from services.simulation.render import integrate_pixels, subsample_rays
from services.simulation.scene import Scene
from services.simulation.temperature import Spot, SurfaceTemperature, TemperatureScene, surface_temperature


class ThermalEffects(BaseModel):
    """The thermal camera's imperfections.

    ``supersample`` x ``supersample`` rays per pixel (an odd number) integrate its area;
    ``blur_sigma`` is the optics' Gaussian blur in pixels; ``netd`` the noise
    equivalent temperature difference in kelvin (Gaussian noise of that standard
    deviation at every temperature). Area integration and blur act on radiance
    (counts on ``planck``'s curve), not on temperature, as in a real camera.
    ``measuring_range`` (lowest, highest) degrees C is the gain mode's range
    (``THERMAL_RANGES``): a pixel at or beyond it is saturated and reads NaN, never
    a clipped temperature; None measures any temperature.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    supersample: int = Field(3, ge=1, le=7)
    blur_sigma: float = Field(0.6, ge=0.0)
    netd: float = Field(0.05, ge=0.0)
    planck: PlanckConstants = Field(default_factory=PlanckConstants)
    measuring_range: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _range_is_ordered(self) -> ThermalEffects:
        if self.measuring_range is not None and not self.measuring_range[0] < self.measuring_range[1]:
            raise ValueError(f"measuring_range must be (lowest, highest) degrees C; got {self.measuring_range}")
        return self


# Measuring ranges (degrees C) of thermal camera gain modes. The OAK Thermal's core is an InfiRay TINY1C
# (Luxonis product page); its two gain modes as InfiRay's datasheet is commonly quoted. A hot-forging
# camera needs a high-temperature range such as the last (a radiometric short-wave or long-wave camera
# with a high-temperature filter, e.g. 300..1500 C).
THERMAL_RANGES: dict[str, tuple[float, float]] = {
    "tiny1c_high_gain": (-20.0, 150.0),
    "tiny1c_low_gain": (0.0, 550.0),
    "forging_high_range": (300.0, 1500.0),
}


def render_thermal(
    scene: Scene,
    temperatures: TemperatureScene,
    device: CameraModel,
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
    device : CameraModel
        The thermal camera (intrinsics, distortion and pose).
    effects : ThermalEffects
        Area integration, blur and noise.
    rng : numpy.random.Generator
        Source of the noise.

    Returns
    -------
    image : (height, width) float32 array
        Temperature per pixel; NaN at or beyond the effects' measuring range.

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
    if effects.measuring_range is not None:
        lowest, highest = effects.measuring_range
        image = np.where((image > lowest) & (image < highest), image, np.nan)
    return image.astype(np.float32)


def seen_by(scene: Scene, device: CameraModel, points: np.ndarray, tolerance_mm: float = 0.5) -> np.ndarray:
    """Ground truth visibility: whether the device's line of sight to each point (N, 3) is unobstructed.

    A point is seen when the first scene hit along the ray from the device
    centre toward it is no nearer than the point itself, less ``tolerance_mm``.
    Pixel bounds are not checked.
    """
    points = np.asarray(points, dtype=np.float64)
    centre = device.centre
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


__all__ = ["THERMAL_RANGES", "Spot", "SurfaceTemperature", "TemperatureScene", "ThermalEffects", "forging_temperatures",
           "render_thermal", "seen_by", "surface_temperature"]
