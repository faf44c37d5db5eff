"""What a visible camera captures of a glowing part: reflected patterns plus the part's own emission,
through a sensor modelled in physical units (electrons, full well, read and shot noise, ADC bits).

Per camera sub-sample X, in units of full projector light on a white surface at normal incidence:

    E(t) = rho(X) (ambient + lit(X) cos(theta_p) L(x_p(X))) + G(T(X, t))

with the geometry of ``render.render_view`` and G(T) = glow_rate(T) / white_rate from
``Optics`` (Planck's law through the camera's band), T cooling at each surface's rate during the
capture. The pixel's electrons are N ~ Poisson(white_rate * exposure * E) + read noise, clipped at the
full well, and its grey level round(N / gain) clipped to the ADC's range. See docs/hot-parts.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from services.geometry.camera_model import CameraModel
from services.simulation.optics import Optics, SensorOptics
from services.simulation.raycast import cast_rays
from services.simulation.render import ProjectorEffects, ViewGeometry, integrate_pixels, sample_irradiance, subsample_rays
from services.simulation.scene import Scene
from services.simulation.temperature import surface_temperature


@dataclass(frozen=True)
class GlowView:
    """Per camera sub-sample (H * s, W * s): temperature at the start of the capture (degrees C) and
    cooling rate (K/s); ``optics`` turns them into glow."""

    optics: Optics
    supersample: int
    temperature: np.ndarray = field(repr=False)
    cooling: np.ndarray = field(repr=False)

    def glow(self, time_s: float) -> np.ndarray:
        """Sub-sample glow ``time_s`` seconds into the capture, in units of full projector light on white."""
        return self.optics.relative_glow(self.temperature - self.cooling * np.float32(time_s))

    def pixel_glow(self, time_s: float) -> np.ndarray:
        """Glow per camera pixel (area-integrated), same units."""
        return integrate_pixels(self.glow(time_s), self.supersample)


def render_glow_view(scene: Scene, camera: CameraModel, supersample: int = 3) -> GlowView:
    """Trace the temperature seen through every camera sub-sample of a hot scene.

    Parameters
    ----------
    scene : Scene
        With ``temperature`` and ``optics``.
    camera : CameraModel
        The visible camera.
    supersample : int
        Odd number of sub-samples per pixel side; the same as the ``render_view`` it goes with.

    Returns
    -------
    GlowView
    """
    if scene.temperature is None or scene.optics is None:
        raise ValueError("A glowing scene needs both 'temperature' and 'optics'; this scene lacks "
                         + " and ".join(name for name in ("temperature", "optics") if getattr(scene, name) is None)
                         + ".")
    origin, directions = subsample_rays(camera, supersample)
    hits = cast_rays(scene, origin, directions)
    temperature = surface_temperature(scene.temperature, hits.points, hits.surface)
    rates = np.array([surface.cooling_rate for surface in scene.temperature.surfaces] + [0.0])
    shape = (camera.height * supersample, camera.width * supersample)
    return GlowView(optics=scene.optics, supersample=supersample,
                    temperature=temperature.astype(np.float32).reshape(shape),
                    cooling=rates[hits.surface].astype(np.float32).reshape(shape))


def expose_sensor(irradiance: np.ndarray, sensor: SensorOptics, white_rate: float, exposure_s: float,
                  rng: np.random.Generator, blur_sigma: float = 0.0) -> np.ndarray:
    """Grey levels of a pixel irradiance image (units of full projector light on white) after an exposure.

    Parameters
    ----------
    irradiance : (H, W) array
        Pixel irradiance, relative.
    sensor : SensorOptics
        Full well, read noise, bit depth.
    white_rate : float
        Electrons per second per pixel at irradiance 1 (``Optics.white_rate``).
    exposure_s : float
        Exposure time in seconds.
    rng : numpy.random.Generator
        Source of shot and read noise.
    blur_sigma : float
        The lens's Gaussian defocus in pixels, applied to the irradiance.

    Returns
    -------
    frame : (H, W) uint8 (8 bits) or uint16 (10, 12 bits) array

    Notes
    -----
    N = min(Poisson(white_rate t E) + N(0, read_noise^2), full_well) electrons, grey = round(N / g) with
    g = full_well / (2^bits - 1), clipped to [0, 2^bits - 1] [1]_.

    References
    ----------
    .. [1] EMVA Standard 1288, "Standard for characterization of image sensors and cameras", release 4.0, 2021.
    """
    if exposure_s <= 0:
        raise ValueError(f"The exposure time must be positive; got {exposure_s} s.")
    irradiance = np.asarray(irradiance, dtype=np.float32)
    if blur_sigma > 0:
        irradiance = cv2.GaussianBlur(irradiance, (0, 0), blur_sigma, borderType=cv2.BORDER_REPLICATE)
    mean_electrons = np.maximum(irradiance, 0).astype(np.float64) * (white_rate * exposure_s)
    # Far beyond the full well the count only needs to saturate: cap the Poisson mean to keep it finite.
    electrons = rng.poisson(np.minimum(mean_electrons, 4 * sensor.full_well_e)).astype(np.float32)
    if sensor.read_noise_e > 0:
        electrons += np.float32(sensor.read_noise_e) * rng.standard_normal(electrons.shape, dtype=np.float32)
    grey = np.rint(np.clip(electrons, 0, sensor.full_well_e) / np.float32(sensor.gain_e_per_dn))
    return np.clip(grey, 0, sensor.full_scale).astype(sensor.dtype)


def render_hot_frames(view: ViewGeometry, glow: GlowView, patterns: np.ndarray, exposure_s: float,
                      rng: np.random.Generator, *, frame_interval_s: float = 1 / 30, start_s: float = 0.0,
                      blur_sigma: float = 0.0, projector_effects: ProjectorEffects = ProjectorEffects()) -> np.ndarray:
    """Camera frames of a glowing scene for each projected pattern, the part cooling between frames.

    Parameters
    ----------
    view : ViewGeometry
        From ``render_view`` (same camera and supersample as ``glow``).
    glow : GlowView
        From ``render_glow_view``.
    patterns : (F, Hp, Wp) integer array
        Projector images in display order.
    exposure_s : float
        Exposure time of every frame, seconds.
    rng : numpy.random.Generator
        Noise source.
    frame_interval_s : float
        Time from one frame to the next (the part cools meanwhile).
    start_s : float
        Time of the first frame since the temperatures were stated.
    blur_sigma : float
        Camera defocus in pixels.
    projector_effects : ProjectorEffects
        Projector gamma, black level and defocus.

    Returns
    -------
    frames : (F, H, W) uint8 or uint16 array
        See ``expose_sensor``.
    """
    if glow.temperature.shape != view.direct.shape:
        raise ValueError("The glow view and the projector view must come from the same camera and supersample.")
    projector, sensor = view.projector, glow.optics.sensor
    patterns = np.asarray(patterns)
    if patterns.ndim != 3 or patterns.shape[1:] != (projector.height, projector.width):
        raise ValueError(f"patterns must have shape (F, {projector.height}, {projector.width}); got {patterns.shape}.")
    frames = np.empty((len(patterns), view.camera.height, view.camera.width), dtype=sensor.dtype)
    cooling = bool(np.any(glow.cooling > 0))
    emitted = None if cooling else glow.glow(start_s)
    for index, pattern in enumerate(patterns):
        if cooling:
            emitted = glow.glow(start_s + index * frame_interval_s)
        samples = sample_irradiance(view, pattern, projector_effects)
        samples += emitted
        irradiance = integrate_pixels(samples, view.supersample)
        frames[index] = expose_sensor(irradiance, sensor, glow.optics.white_rate, exposure_s, rng, blur_sigma)
    return frames
