"""What a camera captures of a scene lit by a projector: a geometry pass once, then a cheap pass per pattern.

The image model, per camera sub-sample X (world point seen through it) with albedo rho(X):

    E = rho(X) * (ambient + lit(X) * cos(theta_p) * L(x_p(X)))

where x_p(X) is the (distorted) projector pixel of X, L the projector light there (pattern value
through the projector's gamma, black level and defocus blur), theta_p the angle between the surface
normal and the direction to the projector, and lit(X) says that X faces the projector, falls inside its
image and is not shadowed (the projector's own ray to X meets nothing nearer). Sub-samples are averaged
over each camera pixel (area integration), then the camera applies defocus blur, exposure, gamma,
sensor noise and quantisation with saturation.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache
from typing import Protocol

import cv2
import numpy as np

from services.geometry.camera import normalized_coordinates, pixel_grid, project_points
from services.geometry.camera_model import CameraModel
from services.simulation.raycast import cast_rays
from services.simulation.scene import Scene, surface_albedo

_SHADOW_TOLERANCE_MM = 1e-3
_UNLIT = -1.0  # remap coordinate of unlit samples, whose light weight is zero anyway
_SAMPLES_PER_BLOCK = 1 << 19  # camera rays traced at a time, bounding memory to a few hundred MB
_IDEAL_MARGIN = 0.25  # accept projector pixels whose distortion-free projection is within 25% beyond the image


@dataclass(frozen=True)
class ProjectorEffects:
    """How a projector turns pattern values into light.

    light = black_level + (1 - black_level) * (value / max_value) ** gamma, then Gaussian defocus blur
    of ``blur_sigma`` projector pixels (0 for none).
    """

    gamma: float = 1.0
    black_level: float = 0.0
    blur_sigma: float = 0.0

    def __post_init__(self) -> None:
        if self.gamma <= 0:
            raise ValueError(f"The projector gamma must be positive; got {self.gamma}.")
        if not 0 <= self.black_level < 1:
            raise ValueError(f"The projector black level must be in [0, 1); got {self.black_level}.")
        if self.blur_sigma < 0:
            raise ValueError(f"The projector blur sigma must be non-negative; got {self.blur_sigma}.")


@dataclass(frozen=True)
class CameraEffects:
    """How a camera turns irradiance into grey levels.

    grey = full_scale * (exposure * E) ** (1 / gamma) after Gaussian defocus blur of ``blur_sigma``
    camera pixels; then Gaussian noise of variance noise_sigma^2 + shot_noise_gain * grey (grey levels
    of the output bit depth); then rounding and clipping to [0, full_scale] (saturation).
    ``exposure`` is the fraction of full scale that full projector light on a white surface at normal
    incidence produces.
    """

    exposure: float = 0.8
    gamma: float = 1.0
    blur_sigma: float = 0.0
    noise_sigma: float = 0.0
    shot_noise_gain: float = 0.0
    bit_depth: int = 8

    def __post_init__(self) -> None:
        if self.exposure <= 0 or self.gamma <= 0:
            raise ValueError(f"The camera exposure and gamma must be positive; got {self.exposure}, {self.gamma}.")
        if min(self.blur_sigma, self.noise_sigma, self.shot_noise_gain) < 0:
            raise ValueError("The camera blur sigma, noise sigma and shot-noise gain must be non-negative.")
        if self.bit_depth not in (8, 16):
            raise ValueError(f"The camera bit depth must be 8 or 16; got {self.bit_depth}.")

    @property
    def dtype(self) -> type:
        return np.uint8 if self.bit_depth == 8 else np.uint16

    @property
    def full_scale(self) -> int:
        return (1 << self.bit_depth) - 1


@dataclass(frozen=True)
class GroundTruth:
    """What the simulator knows about each camera pixel (its centre ray), NaN / -1 / False where it misses.

    Attributes
    ----------
    depth : (H, W) array
        Camera-frame z of the surface point in mm.
    points : (H, W, 3) array
        World surface point in mm.
    surface : (H, W) int array
        Index into ``scene.surfaces``.
    lit : (H, W) bool array
        Every sub-sample of the pixel sees a surface that faces the projector, falls inside its image
        and is not shadowed.
    projector_pixels : (H, W, 2) array
        Distorted projector pixel (u, v) of the centre point where that point is lit.
    """

    depth: np.ndarray
    points: np.ndarray
    surface: np.ndarray
    lit: np.ndarray
    projector_pixels: np.ndarray


@dataclass(frozen=True)
class ViewGeometry:
    """The pattern-independent part of a camera's view of a projector-lit scene.

    Sub-sample arrays have shape (H * s, W * s) for ``supersample`` s: the projector coordinates each
    sub-sample reads (float32 maps for ``cv2.remap``), the weight of projector light there
    (albedo * cos(theta_p), 0 when unlit) and the ambient term (albedo * ambient).
    """

    camera: CameraModel
    projector: CameraModel
    supersample: int
    projector_x: np.ndarray = field(repr=False)
    projector_y: np.ndarray = field(repr=False)
    direct: np.ndarray = field(repr=False)
    ambient: np.ndarray = field(repr=False)
    truth: GroundTruth = field(repr=False)


def subsample_offsets(supersample: int) -> np.ndarray:
    """Offsets (s,) of s evenly spaced sub-samples across a pixel, centred on it: (k + 1/2) / s - 1/2."""
    if supersample < 1 or supersample % 2 == 0:
        raise ValueError(f"supersample must be a positive odd number (the centre sample is the pixel centre); "
                         f"got {supersample}.")
    return (np.arange(supersample) + 0.5) / supersample - 0.5


def subsample_rays(device: CameraModel, supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """World rays through an s x s grid of sub-samples in every pixel of ``device``.

    Returns
    -------
    origin : (3,) array
        Device centre.
    directions : (H * s * W * s, 3) array
        Unit directions in the row-major order of the (H * s, W * s) sub-sample image.

    Notes
    -----
    Pixel centres are undistorted exactly (``normalized_coordinates``). Off-centre sub-samples use the
    first-order expansion n(p + delta) = n(p) + J(p) delta with the Jacobian J from second-order finite
    differences of the exact centres: one exact undistortion per pixel instead of s^2, and an error
    below 1e-5 pixel for realistic lenses, far below what shading can show.
    """
    offsets = subsample_offsets(supersample)
    width, height = device.width, device.height
    centres = normalized_coordinates(pixel_grid(width, height), device.K, device.dist)
    centres = centres.reshape(height, width, 2)
    edge_order = 2 if min(width, height) > 2 else 1
    d_du = np.gradient(centres, axis=1, edge_order=edge_order) if width > 1 else np.zeros_like(centres)
    d_dv = np.gradient(centres, axis=0, edge_order=edge_order) if height > 1 else np.zeros_like(centres)
    row_offsets, column_offsets = offsets[None, :, None, None], offsets[None, None, None, :]
    x, y = ((centres[:, None, :, None, axis] + row_offsets * d_dv[:, None, :, None, axis]
             + column_offsets * d_du[:, None, :, None, axis]).ravel() for axis in (0, 1))
    inverse_length = 1 / np.sqrt(x * x + y * y + 1)  # rotating the device ray (x, y, 1) keeps its length
    R = device.R
    directions = np.empty((x.size, 3))
    for axis in range(3):  # world direction R^T (x, y, 1), one component at a time to spare memory
        directions[:, axis] = (x * R[0, axis] + y * R[1, axis] + R[2, axis]) * inverse_length
    return device.centre, directions


def integrate_pixels(samples: np.ndarray, supersample: int) -> np.ndarray:
    """Average an (H * s, W * s [, ...]) sub-sample image over each pixel's s x s block -> (H, W [, ...]).

    With s = 1 the samples are the pixels: returned as they are (not copied).
    """
    if supersample == 1:
        return samples
    height, width = samples.shape[0] // supersample, samples.shape[1] // supersample
    blocks = samples.reshape((height, supersample, width, supersample) + samples.shape[2:])
    return blocks.mean(axis=(1, 3))


def _projector_pixels(points: np.ndarray, projector: CameraModel) -> np.ndarray:
    """Distorted projector pixels of world points; NaN outside the image or where distortion is extrapolated.

    Only points whose distortion-free projection lies in front of the projector and within 25% beyond its
    image are projected through the distortion model, which wraps around far outside the calibrated field.
    """
    R, t, K = projector.R, projector.t, projector.K
    depth = points @ R[2] + t[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = (points @ R[0] + t[0]) / depth, (points @ R[1] + t[1]) / depth
    ideal = np.column_stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]])
    margin_u, margin_v = _IDEAL_MARGIN * projector.width, _IDEAL_MARGIN * projector.height
    near_image = ((depth > 0) & (ideal[:, 0] >= -margin_u) & (ideal[:, 0] <= projector.width + margin_u)
                  & (ideal[:, 1] >= -margin_v) & (ideal[:, 1] <= projector.height + margin_v))
    pixels = np.full((len(points), 2), np.nan)
    if projector.dist.any():
        pixels[near_image] = project_points(points[near_image], projector.K, projector.dist,
                                            projector.R, projector.t)
    else:
        pixels[near_image] = ideal[near_image]
    with np.errstate(invalid="ignore"):
        outside = ~((pixels[:, 0] >= -0.5) & (pixels[:, 0] <= projector.width - 0.5)
                    & (pixels[:, 1] >= -0.5) & (pixels[:, 1] <= projector.height - 0.5))
    pixels[outside] = np.nan
    return pixels


def render_view(scene: Scene, camera: CameraModel, projector: CameraModel, supersample: int = 3) -> ViewGeometry:
    """Trace a camera's view of a scene lit by a projector, once for any number of patterns.

    Parameters
    ----------
    scene : Scene
        Surfaces and ambient light.
    camera, projector : CameraModel
        The viewing device (any kind) and the projector, with intrinsics, distortion and pose.
    supersample : int
        Odd number s of sub-samples per pixel side (s^2 rays per pixel integrate the pixel area).

    Returns
    -------
    ViewGeometry
        Projector coordinates, shading and ambient terms per sub-sample, and the ground truth per pixel.

    Notes
    -----
    A sub-sample sees the surface point X its ray meets first. X is lit when its unit normal n
    (turned toward the camera) faces the projector centre C_p (cos(theta_p) = n . (C_p - X) / |C_p - X| > 0),
    its projector pixel lies in the projector image, and the ray from C_p toward X meets no surface
    nearer than |C_p - X| (projector shadow). Shading is Lambertian [1]_.

    References
    ----------
    .. [1] J. H. Lambert, Photometria, 1760; see e.g. Szeliski, Computer Vision: Algorithms and
       Applications, section 2.2 (2022).
    """
    origin, directions = subsample_rays(camera, supersample)
    height, width, s = camera.height, camera.width, supersample
    samples_per_row = width * s * s
    shape = (height * s, width * s)
    maps = np.empty((height * s * width * s, 2), dtype=np.float32)
    direct = np.empty(maps.shape[0], dtype=np.float32)
    ambient = np.empty(maps.shape[0], dtype=np.float32)
    lit = np.empty(maps.shape[0], dtype=bool)
    centre = {"points": np.empty((height, width, 3)), "surface": np.empty((height, width), dtype=np.int64),
              "lit": np.empty((height, width), dtype=bool), "projector_pixels": np.empty((height, width, 2))}
    rows_per_block = max(1, _SAMPLES_PER_BLOCK // samples_per_row)
    for top in range(0, height, rows_per_block):
        rows = slice(top, min(height, top + rows_per_block))
        block = slice(rows.start * samples_per_row, rows.stop * samples_per_row)
        traced = _trace_samples(scene, origin, directions[block], projector)
        maps[block] = np.where(traced.lit[:, None], traced.projector_pixels, _UNLIT)
        direct[block] = traced.direct
        ambient[block] = traced.albedo * scene.ambient
        lit[block] = traced.lit
        grid = (rows.stop - rows.start, s, width, s)
        for name, values in centre.items():
            values[rows] = _centre_samples(getattr(traced, name), grid)
    grid = (height, s, width, s)
    points = centre["points"]
    truth = GroundTruth(depth=points @ camera.R[2] + camera.t[2], points=points,
                        surface=centre["surface"], lit=lit.reshape(grid).all(axis=(1, 3)),
                        projector_pixels=np.where(centre["lit"][..., None], centre["projector_pixels"], np.nan))
    return ViewGeometry(camera=camera, projector=projector, supersample=supersample,
                        projector_x=maps[:, 0].reshape(shape), projector_y=maps[:, 1].reshape(shape),
                        direct=direct.reshape(shape), ambient=ambient.reshape(shape), truth=truth)


@dataclass(frozen=True)
class _TracedSamples:
    """Per camera sub-sample: surface point and index, lit flag, projector pixel, albedo, light weight."""

    points: np.ndarray
    surface: np.ndarray
    lit: np.ndarray
    projector_pixels: np.ndarray
    albedo: np.ndarray
    direct: np.ndarray


def _trace_samples(scene: Scene, origin: np.ndarray, directions: np.ndarray, projector: CameraModel) -> _TracedSamples:
    """Hit, shadow and shading of one block of camera rays (see ``render_view``)."""
    hits = cast_rays(scene, origin, directions)
    hit = hits.surface >= 0
    projector_centre = projector.centre
    to_projector = projector_centre - hits.points
    distance_to_projector = np.sqrt(np.einsum("ij,ij->i", to_projector, to_projector))
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.einsum("ij,ij->i", hits.normals, to_projector) / distance_to_projector
    candidate = hit & (cosine > 0)
    projector_pixels = np.full((len(directions), 2), np.nan)
    projector_pixels[candidate] = _projector_pixels(hits.points[candidate], projector)
    candidate &= np.isfinite(projector_pixels[:, 0])
    shadow_hits = cast_rays(scene, projector_centre, -to_projector[candidate])
    lit = np.zeros(len(directions), dtype=bool)
    lit[candidate] = shadow_hits.distance >= distance_to_projector[candidate] - _SHADOW_TOLERANCE_MM
    albedo = np.zeros(len(directions))
    albedo[hit] = surface_albedo(scene, hits.points[hit], hits.surface[hit])
    return _TracedSamples(points=hits.points, surface=hits.surface, lit=lit, projector_pixels=projector_pixels,
                          albedo=albedo, direct=np.where(lit, albedo * cosine, 0.0))


def _centre_samples(samples: np.ndarray, grid: tuple[int, int, int, int]) -> np.ndarray:
    """The centre sub-sample of each pixel: (rows * s * W * s, ...) -> (rows, W, ...)."""
    return samples.reshape(grid + samples.shape[1:])[:, grid[1] // 2, :, grid[3] // 2]


def projector_light(pattern: np.ndarray, effects: ProjectorEffects) -> np.ndarray:
    """Relative light (0..1, float32) a projector emits for one pattern image."""
    if pattern.dtype == np.uint8:  # a 256-entry table of the same float32 arithmetic: identical, 10x cheaper
        light = cv2.LUT(pattern, _light_table(effects))
    else:
        maximum = np.iinfo(pattern.dtype).max if np.issubdtype(pattern.dtype, np.integer) else 1.0
        light = _emitted_light(pattern, maximum, effects)
    if effects.blur_sigma > 0:
        light = cv2.GaussianBlur(light, (0, 0), effects.blur_sigma, borderType=cv2.BORDER_REPLICATE)
    return light


def _emitted_light(values: np.ndarray, maximum: float, effects: ProjectorEffects) -> np.ndarray:
    """black_level + (1 - black_level) * (value / maximum) ** gamma in float32, before the defocus blur."""
    light = (values.astype(np.float32) / np.float32(maximum)) ** np.float32(effects.gamma)
    return np.float32(effects.black_level) + np.float32(1 - effects.black_level) * light


@cache
def _light_table(effects: ProjectorEffects) -> np.ndarray:
    """The light of every 8-bit pattern value, for ``cv2.LUT``."""
    return _emitted_light(np.arange(256, dtype=np.uint8), 255, effects)


def sample_irradiance(view: ViewGeometry, pattern: np.ndarray, effects: ProjectorEffects) -> np.ndarray:
    """Irradiance E = direct * L + ambient of every camera sub-sample under one pattern (float32, (H * s, W * s)).

    Projector light is sampled bilinearly at the projector pixel of every sub-sample with ``cv2.remap``
    (edge pixels extend to the image border at -1/2 and size - 1/2).
    """
    irradiance = cv2.remap(projector_light(pattern, effects), view.projector_x, view.projector_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE)
    irradiance *= view.direct
    irradiance += view.ambient
    return irradiance


def render_frames(view: ViewGeometry, patterns: np.ndarray, rng: np.random.Generator,
                  camera_effects: CameraEffects = CameraEffects(),
                  projector_effects: ProjectorEffects = ProjectorEffects()) -> np.ndarray:
    """Camera frames of the view for each projected pattern.

    Parameters
    ----------
    view : ViewGeometry
        From ``render_view``.
    patterns : (F, Hp, Wp) integer array
        Projector images (usually uint8) of the projector's size.
    rng : numpy.random.Generator
        Source of sensor noise (frames are deterministic given its state).
    camera_effects, projector_effects : CameraEffects, ProjectorEffects
        Sensor and projector models.

    Returns
    -------
    frames : (F, H, W) uint8 or uint16 array
        Quantised camera frames.

    Notes
    -----
    Projector light is sampled bilinearly at the projector pixel of every sub-sample
    (:func:`sample_irradiance`), combined as E = direct * L + ambient, and averaged per pixel. See the
    module docstring for the full model.
    """
    patterns = np.asarray(patterns)
    projector = view.projector
    if patterns.ndim != 3 or patterns.shape[1:] != (projector.height, projector.width):
        raise ValueError(f"patterns must have shape (F, {projector.height}, {projector.width}) for the "
                         f"{projector.width}x{projector.height} projector; got {patterns.shape}.")
    frames = np.empty((len(patterns), view.camera.height, view.camera.width), dtype=camera_effects.dtype)
    for index, pattern in enumerate(patterns):
        frames[index] = sensor_levels(pixel_irradiance(view, pattern, camera_effects, projector_effects),
                                      camera_effects, rng)
    return frames


def pixel_irradiance(view: ViewGeometry, pattern: np.ndarray, camera_effects: CameraEffects,
                     projector_effects: ProjectorEffects) -> np.ndarray:
    """Irradiance (float32, (H, W)) of each camera pixel under one pattern, area-integrated and through the
    lens's defocus blur: all of a frame but exposure, noise and quantisation (:func:`sensor_levels`), so the
    same for every frame of a static scene under that pattern."""
    samples = sample_irradiance(view, pattern, projector_effects)
    return defocus(integrate_pixels(samples, view.supersample), camera_effects)


def expose(irradiance: np.ndarray, effects: CameraEffects, rng: np.random.Generator) -> np.ndarray:
    """Turn a pixel irradiance image (relative to full projector light on white) into quantised grey levels.

    Applies the camera's defocus blur (:func:`defocus`), then exposure, gamma, Gaussian read and shot noise,
    rounding and saturation (:func:`sensor_levels`; see ``CameraEffects``).
    """
    return sensor_levels(defocus(irradiance, effects), effects, rng)


def defocus(irradiance: np.ndarray, effects: CameraEffects) -> np.ndarray:
    """The camera lens's Gaussian defocus blur of ``blur_sigma`` pixels, as float32."""
    irradiance = np.asarray(irradiance, dtype=np.float32)
    if effects.blur_sigma > 0:
        irradiance = cv2.GaussianBlur(irradiance, (0, 0), effects.blur_sigma, borderType=cv2.BORDER_REPLICATE)
    return irradiance


class StandardNormalSource(Protocol):
    """Where a frame's sensor noise comes from: a numpy Generator, or deviates drawn ahead of the frame."""

    def standard_normal(self, size: tuple[int, ...], dtype: type) -> np.ndarray: ...


def sensor_levels(irradiance: np.ndarray, effects: CameraEffects, rng: StandardNormalSource) -> np.ndarray:
    """Quantised grey levels of a defocused pixel irradiance image: exposure, gamma, Gaussian read and shot
    noise, rounding and saturation (see ``CameraEffects``). The noise is one ``rng.standard_normal`` image
    (float32) per frame, scaled per pixel."""
    grey = np.multiply(np.asarray(irradiance, dtype=np.float32), np.float32(effects.exposure))  # then in place
    np.maximum(grey, 0, out=grey)
    if effects.gamma != 1:
        np.power(grey, np.float32(1 / effects.gamma), out=grey)
    grey *= np.float32(effects.full_scale)
    read_variance = np.float32(effects.noise_sigma**2)
    if effects.shot_noise_gain > 0:
        sigma = np.sqrt(read_variance + np.float32(effects.shot_noise_gain) * grey)
    else:
        sigma = np.sqrt(read_variance)
    if np.any(sigma > 0):
        noise = rng.standard_normal(grey.shape, dtype=np.float32)
        noise *= sigma
        grey += noise
    np.rint(grey, out=grey)
    np.clip(grey, 0, effects.full_scale, out=grey)
    return grey.astype(effects.dtype)
