"""The 3D temperature field: each cloud point's temperature from one or more calibrated thermal views."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np

from services.geometry.camera_model import CameraModel
from services.geometry.rigid import rigid_transform
from services.fusion.visibility import (
    SAMPLE_FOOTPRINTS, depth_buffer, depth_gradient, depth_tolerance, nearest_depth_around, seen_mask,
)
from services.geometry.camera import project_points

DEFAULT_MAX_VIEW_ANGLE_DEG = 75.0
DEFAULT_DEPTH_TOLERANCE_MM = 2.0
DEFAULT_OCCLUSION_MARGIN_PX = 6


@dataclass(frozen=True)
class ThermalView:
    """Frames of one calibrated thermal camera, in degrees Celsius, shape (F, height, width)."""

    device: CameraModel
    frames: np.ndarray

    def __post_init__(self) -> None:
        frames = np.asarray(self.frames)
        if frames.ndim == 2:
            frames = frames[None]
        expected = (self.device.height, self.device.width)
        if frames.ndim != 3 or frames.shape[1:] != expected:
            raise ValueError(
                f"Thermal frames must be (F, {expected[0]}, {expected[1]}) for this device; got {frames.shape}."
            )
        object.__setattr__(self, "frames", frames.astype(np.float64, copy=False))


@dataclass(frozen=True)
class TemperatureField:
    """Per-point fused temperature (degrees C, NaN unseen) and best view angle (degrees, NaN unseen)."""

    temperature: np.ndarray
    view_angle: np.ndarray


def view_angles(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Angle between each normal and the direction from its point to ``centre``, radians (NaN if unknown)."""
    angles = np.empty(len(points))
    _view_angles(np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
                 np.asarray(centre, dtype=np.float64), angles)
    return angles


# Compiled per-point loops: numpy's whole-array expressions over a scan's half a million points made a dozen
# temporaries each (the bilinear sampling took 4x as long, the whole fusion 2.6x). nogil: the service's other threads (API, artifact writers)
# run meanwhile.
@numba.njit(cache=True, nogil=True)
def _view_angles(points, normals, centre, out):
    for i in range(points.shape[0]):
        x, y, z = centre[0] - points[i, 0], centre[1] - points[i, 1], centre[2] - points[i, 2]
        length = np.sqrt(x * x + y * y + z * z)
        cosine = (x / length) * normals[i, 0] + (y / length) * normals[i, 1] + (z / length) * normals[i, 2]
        out[i] = np.arccos(min(max(cosine, -1.0), 1.0)) if np.isfinite(cosine) else np.nan


def _project(points: np.ndarray, device: CameraModel) -> np.ndarray:
    """Distorted pixel coordinates of world points in the device."""
    return project_points(points, device.K, device.dist, device.R, device.t)


def _bilinear_samples(
    frames: np.ndarray, pixels: np.ndarray, depth: np.ndarray, buffer: np.ndarray, tolerance: np.ndarray
) -> np.ndarray:
    """Depth-aware bilinear samples (F, N) of the frames at the points' pixels.

    Each of the four neighbouring pixel centres counts only if its z-buffer depth
    shows the point's own surface there (not a nearer occluder or empty space)
    and the frame is finite there; the bilinear weights of the counted corners
    are renormalised. NaN where no corner counts, and where a corner of non-zero
    weight on the point's surface has no finite value: a point beside a pixel
    without a temperature (saturated, beyond the range) gets none rather than the
    lower temperature of its other neighbours.
    """
    samples = np.empty((len(frames), len(depth)))
    _bilinear_kernel(np.ascontiguousarray(frames, dtype=np.float64), np.ascontiguousarray(pixels, dtype=np.float64),
                     np.ascontiguousarray(depth, dtype=np.float64), np.ascontiguousarray(buffer, dtype=np.float64),
                     np.ascontiguousarray(tolerance, dtype=np.float64), samples)
    return samples


@numba.njit(cache=True, nogil=True)
def _bilinear_kernel(frames, pixels, depth, buffer, tolerance, out):
    count, height, width = frames.shape
    for i in range(pixels.shape[0]):
        left, top = np.floor(pixels[i, 0]), np.floor(pixels[i, 1])
        fx, fy = pixels[i, 0] - left, pixels[i, 1] - top
        for frame in range(count):
            total, weight_sum, unknown = 0.0, 0.0, False
            for corner in range(4):
                dx, dy = corner % 2, corner // 2
                column, row = left + dx, top + dy
                if not (column >= 0 and column < width and row >= 0 and row < height):
                    continue
                r, c = int(row), int(column)
                if not depth[i] <= buffer[r, c] + tolerance[i]:  # a nearer surface (or none) at this corner
                    continue
                weight = (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy)
                value = frames[frame, r, c]
                if np.isfinite(value):
                    total += value * weight
                    weight_sum += weight
                elif weight > 0:
                    unknown = True
            out[frame, i] = total / weight_sum if weight_sum > 0 and not unknown else np.nan


def sample_view(
    points: np.ndarray,
    normals: np.ndarray,
    view: ThermalView,
    max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
    depth_tolerance_mm: float = DEFAULT_DEPTH_TOLERANCE_MM,
    occlusion_margin_px: int = DEFAULT_OCCLUSION_MARGIN_PX,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Temperature of each point in one thermal view, averaged over the view's frames.

    See :func:`fuse_temperature` for the parameters.

    Returns
    -------
    temperature : (N,) float64 array
        NaN where the view does not see the point, sees it beyond the angle
        limit, or the frames have no finite value there.
    view_angle : (N,) float64 array
        Radians, for points the view sees (in the image and not occluded); NaN
        otherwise.
    weight : (N,) float64 array
        cos(view angle) times the number of frames that gave a value; 0 where
        ``temperature`` is NaN.
    """
    device = view.device
    max_angle = np.deg2rad(max_view_angle_deg)
    pixels = _project(points, device)
    points_device = rigid_transform(points, device.R, device.t)
    depth = points_device[:, 2]
    angle = view_angles(points, normals, device.centre)
    focal = 0.5 * (device.K[0, 0] + device.K[1, 1])
    gradient = depth_gradient(points_device, rigid_transform(normals, device.R, np.zeros(3)), focal, max_angle)
    tolerance = depth_tolerance(gradient, depth_tolerance_mm)
    buffer = depth_buffer(pixels, depth, device.width, device.height)
    seen = seen_mask(pixels, depth, buffer, tolerance)
    if occlusion_margin_px > 0:
        # the square window reaches margin * sqrt(2) pixels away along its diagonals
        guard = depth_tolerance(gradient, depth_tolerance_mm, SAMPLE_FOOTPRINTS + np.sqrt(2) * occlusion_margin_px)
        seen &= seen_mask(pixels, depth, nearest_depth_around(buffer, occlusion_margin_px), guard)
    usable = seen & (angle <= max_angle)

    temperature = np.full(len(points), np.nan)
    weight = np.zeros(len(points))
    if usable.any():
        samples = _bilinear_samples(view.frames, pixels[usable], depth[usable], buffer, tolerance[usable])
        frames_seen = np.isfinite(samples).sum(axis=0)
        mean = np.nansum(samples, axis=0) / np.maximum(frames_seen, 1)
        temperature[usable] = np.where(frames_seen > 0, mean, np.nan)
        weight[usable] = np.cos(angle[usable]) * frames_seen
    return temperature, np.where(seen, angle, np.nan), weight


def fuse_temperature(
    points: np.ndarray,
    normals: np.ndarray,
    views: Sequence[ThermalView],
    max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
    depth_tolerance_mm: float = DEFAULT_DEPTH_TOLERANCE_MM,
    occlusion_margin_px: int = DEFAULT_OCCLUSION_MARGIN_PX,
) -> TemperatureField:
    """Temperature of every cloud point from calibrated thermal views, fused by view-angle weight.

    Parameters
    ----------
    points : (N, 3) array
        Cloud points in world millimetres.
    normals : (N, 3) array
        Unit outward normals (facing the camera that measured the cloud); NaN
        where unknown (such points use the angle limit for their depth tolerance
        and are sampled only if their angle is known).
    views : sequence of ThermalView
        Thermal cameras with their frames in degrees Celsius.
    max_view_angle_deg : float
        Points seen at a larger angle between normal and line of sight get no
        temperature from that view: emissivity falls toward grazing incidence.
    depth_tolerance_mm : float
        Depth margin of the z-buffer test beyond the slope term (covers the
        cloud's noise).
    occlusion_margin_px : int
        Points within this many pixels of a nearer surface in the thermal view
        are treated as unseen (0 to disable): it guards against occluders the
        cloud lacks (e.g. parts in the projector's shadow) and against the
        optics' blur mixing an occluder's radiance into the pixels beside it.

    Returns
    -------
    TemperatureField
        ``temperature`` (N,) float32 degrees C and ``view_angle`` (N,) float32
        degrees (the smallest over the views that see the point), NaN unseen.

    Notes
    -----
    Each point X projects to distorted pixel coordinates p = pi(K, dist, R X + t)
    in each thermal camera. It is seen if its depth z is within a tolerance of the
    z-buffer of the cloud at p (see :func:`services.fusion.visibility.depth_buffer`),
    so that a hidden point gets NaN rather than its occluder's temperature, and
    no surface nearer by more than the slope-scaled tolerance (over the
    window's reach) lies within the occlusion margin (a guard band at depth discontinuities [2]_). Its
    temperature is the depth-aware bilinear sample at p, averaged over the
    view's frames, and views are fused by

        T = sum_v w_v T_v / sum_v w_v,   w_v = n_v cos(theta_v),

    with theta_v the angle between the normal and the line of sight and n_v the
    number of frames, for theta_v <= theta_max. The cosine weight follows the
    fall of a surface's directional emissivity and the growth of the pixel
    footprint toward grazing angles [1]_.

    References
    ----------
    .. [1] M. Vollmer and K.-P. Moellmann, "Infrared Thermal Imaging", 2nd ed.,
       Wiley-VCH, 2018, sec. 1.4 (directional emissivity).
    .. [2] V. Lempitsky and D. Ivanov, "Seamless Mosaicing of Image-Based
       Texture Maps", CVPR 2007 (rejecting views near depth discontinuities).
    """
    if occlusion_margin_px < 0:
        raise ValueError(f"The occlusion margin must be a non-negative number of pixels; got {occlusion_margin_px}.")
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (N, 3); got {points.shape} and {normals.shape}.")
    if not views:
        raise ValueError("At least one thermal view is needed to fuse a temperature field.")
    if not 0.0 < max_view_angle_deg < 90.0:
        raise ValueError(f"The view-angle limit must be in (0, 90) degrees; got {max_view_angle_deg}.")
    weighted_sum = np.zeros(len(points))
    weight_sum = np.zeros(len(points))
    best_angle = np.full(len(points), np.inf)
    for view in views:
        temperature, angle, weight = sample_view(points, normals, view, max_view_angle_deg, depth_tolerance_mm,
                                                 occlusion_margin_px)
        weighted_sum += np.where(weight > 0, temperature * weight, 0.0)
        weight_sum += weight
        best_angle = np.fmin(best_angle, angle)
    with np.errstate(invalid="ignore", divide="ignore"):
        fused = np.where(weight_sum > 0, weighted_sum / weight_sum, np.nan)
    best_angle[np.isinf(best_angle)] = np.nan
    return TemperatureField(fused.astype(np.float32), np.rad2deg(best_angle).astype(np.float32))
