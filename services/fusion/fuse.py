"""The 3D temperature field: each cloud point's temperature from one or more calibrated thermal views.

The per-point work runs as numpy expressions on chunks of ``POINT_CHUNK`` points, on the small thread pool of
:mod:`services.structured_light.row_bands`: a chunk's float64 temporaries (half a megabyte each) stay in the
CPU cache, where whole-array expressions over a scan's half a million points would each stream several
megabytes through memory, and numpy releases the GIL, so the chunks run in parallel and the service's other
threads (API, artifact writers) run meanwhile.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from services.geometry.camera_model import CameraModel
from services.geometry.distortion import distorted_pixels, opencv_distortion_terms
from services.geometry.rigid import rigid_transform
from services.fusion.carving import UnseenSpace, image_coordinates, occluder_samples
from services.fusion.visibility import (
    SAMPLE_FOOTPRINTS, background_depth, depth_gradient, depth_tolerance, fill_empty_pixels, footprint_radius,
    nearest_depth_around, nearest_pixel_index, splat_nearest, within_tolerance,
)
from services.structured_light.row_bands import map_bands, row_bands

DEFAULT_MAX_VIEW_ANGLE_DEG = 75.0
DEFAULT_DEPTH_TOLERANCE_MM = 2.0
DEFAULT_OCCLUSION_MARGIN_PX = 6
DEFAULT_THERMAL_BLUR_PX = 1.0
"""The thermal optics' Gaussian blur (sigma, pixels) the mixed-pixel test assumes: a conservative value for
uncooled long-wave cameras (the simulator's is 0.6); give the camera's own where it is known."""
POINT_CHUNK = 1 << 16
"""Points per chunk of the per-point passes."""


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
    """Per-point fused temperature (degrees C, NaN unseen) and best view angle (degrees, NaN unseen).

    With an :class:`~services.fusion.carving.UnseenSpace`, ``temperature`` leaves out the readings whose thermal
    ray crosses a skirt, and ``unguarded`` holds the temperatures without that test (``None`` without one)."""

    temperature: np.ndarray
    view_angle: np.ndarray
    unguarded: np.ndarray | None = None


def view_angles(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Angle between each normal and the direction from its point to ``centre``, radians (NaN if unknown)."""
    points, normals = _as_float(points), _as_float(normals)
    centre = np.asarray(centre, dtype=np.float64)
    angles = np.empty(len(points))

    def chunk(rows: slice) -> None:
        angles[rows] = _view_angles(np.asarray(points[rows], dtype=np.float64),
                                    np.asarray(normals[rows], dtype=np.float64), centre)

    map_bands(chunk, _chunks(len(points)))
    return angles


def _chunks(count: int) -> list[slice]:
    return row_bands(count, 1, POINT_CHUNK)


def _as_float(array: np.ndarray) -> np.ndarray:
    """``array`` as it is if float32 or float64 (the chunks convert to float64), else as float64."""
    array = np.asarray(array)
    return array if array.dtype in (np.float32, np.float64) else array.astype(np.float64)


def _view_angles(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """:func:`view_angles` of float64 (n, 3) arrays."""
    cosine = _view_cosines(points, normals, centre)
    return np.arccos(cosine, out=cosine)  # NaN stays NaN


def _view_cosines(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Cosines of :func:`_view_angles`, clipped to [-1, 1] (NaN if unknown)."""
    x, y, z = centre[0] - points[:, 0], centre[1] - points[:, 1], centre[2] - points[:, 2]
    length = x * x
    length += y * y
    length += z * z
    np.sqrt(length, out=length)
    x /= length
    y /= length
    z /= length
    x *= normals[:, 0]
    y *= normals[:, 1]
    z *= normals[:, 2]
    cosine = x
    cosine += y
    cosine += z
    cosine[np.isinf(cosine)] = np.nan
    return np.clip(cosine, -1.0, 1.0, out=cosine)


def _bilinear(frames: np.ndarray, u: np.ndarray, v: np.ndarray, depth: np.ndarray, buffer: np.ndarray,
              tolerance: np.ndarray) -> np.ndarray:
    """Depth-aware bilinear samples (F, n) of the frames at one chunk of points' pixels (u, v).

    Each of the four neighbouring pixel centres counts only if its z-buffer depth shows the point's own
    surface there (not a nearer occluder or empty space) and the frame is finite there; the bilinear
    weights of the counted corners are renormalised. NaN where no corner counts, and where a corner of
    non-zero weight on the point's surface has no finite value: a point beside a pixel without a temperature
    (saturated, beyond the range) gets none rather than the lower temperature of its other neighbours.
    """
    count, height, width = frames.shape
    values_of = frames.reshape(count, -1)
    surface_of = buffer.reshape(-1)
    all_finite = [bool(np.isfinite(values).all()) for values in values_of]
    left, top = np.floor(u), np.floor(v)
    fx, fy = u - left, v - top
    with np.errstate(invalid="ignore"):  # NaN pixels: no corner counts
        left_in, right_in = (left >= 0) & (left < width), (left >= -1) & (left < width - 1)
        top_in, bottom_in = (top >= 0) & (top < height), (top >= -1) & (top < height - 1)
        base = np.where(left_in | right_in, left, 0.0)
        base += np.where(top_in | bottom_in, top, 0.0) * width
        base = base.astype(np.intp)
    total = np.zeros((count, len(u)))
    weight_sum = np.zeros((count, len(u)))
    unknown = np.zeros((count, len(u)), dtype=bool)
    for dy, row_in, row_weight in ((0, top_in, 1.0 - fy), (1, bottom_in, fy)):
        for dx, column_in in ((0, left_in), (1, right_in)):
            counted = row_in & column_in
            flat = base + (dy * width + dx)
            np.clip(flat, 0, height * width - 1, out=flat)  # (corners outside do not count)
            limit = surface_of[flat]
            limit += tolerance
            counted &= depth <= limit  # else a nearer surface (or none) at this corner
            weight = fx * row_weight if dx else (1.0 - fx) * row_weight
            for frame in range(count):
                value = values_of[frame][flat]
                if all_finite[frame]:
                    good = counted
                else:
                    good = np.isfinite(value)
                    unknown[frame] |= (counted & (weight > 0)) > good
                    good &= counted
                value *= weight
                np.add(total[frame], value, out=total[frame], where=good)
                np.add(weight_sum[frame], weight, out=weight_sum[frame], where=good)
    with np.errstate(invalid="ignore", divide="ignore"):
        total /= weight_sum
    total[(weight_sum <= 0) | unknown] = np.nan
    return total


Rows = Callable[[slice], np.ndarray]
"""A chunk's rows of an (N, 3) array, as float64 (n, 3)."""
_ChunkResult = Callable[[slice, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None], None]


def rows_of(array: np.ndarray) -> Rows:
    """:data:`Rows` of an (N, 3) array."""
    return lambda rows: np.asarray(array[rows], dtype=np.float64)


def _sample_view(count: int, points_of: Rows, normals_of: Rows, view: ThermalView, max_view_angle_deg: float,
                 depth_tolerance_mm: float, occlusion_margin_px: int, result: _ChunkResult,
                 thermal_blur_px: float = DEFAULT_THERMAL_BLUR_PX, unseen: UnseenSpace | None = None) -> None:
    """The temperature of ``count`` points in one thermal view, averaged over the view's frames, chunk by chunk:
    ``result(rows, temperature, view_angle, weight, crossed)`` for each chunk of rows (called on the pool's
    threads; each chunk's rows are its own). See :func:`fuse_temperature` for the parameters; ``crossed`` (None
    without ``unseen``) marks the points seen whose thermal ray crosses a skirt of the unseen space.

    ``temperature`` is NaN where the view does not see the point, sees it beyond the angle limit, its pixels
    mix its surface with another, or the frames have no finite value there; ``view_angle`` (radians) is NaN
    where the view does not see the point (outside the image or occluded); ``weight`` is cos(view angle)
    (f / d)^2 times the number of frames that gave a value (f the focal length in pixels, d the distance from
    the camera centre in mm), 0 where ``temperature`` is NaN."""
    device = view.device
    max_angle = np.deg2rad(max_view_angle_deg)
    K = np.asarray(device.K, dtype=np.float64)
    R = np.asarray(device.R, dtype=np.float64)
    t = np.asarray(device.t, dtype=np.float64).ravel()
    terms, tilt = opencv_distortion_terms(device.dist)
    centre = np.asarray(device.centre, dtype=np.float64)
    focal = 0.5 * (K[0, 0] + K[1, 1])
    chunks = _chunks(count)
    pixels = np.empty((2, count))
    depth = np.empty(count)
    index = np.empty(count, dtype=np.intp)

    def project(rows: slice) -> None:  # pixels as services.geometry.camera.project_points, the nearest pixel
        points_device = rigid_transform(points_of(rows), R, t)
        z = points_device[:, 2]
        depth[rows] = z
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(z > 0.0, z, np.nan)
            u, v = distorted_pixels(points_device[:, 0] / z, points_device[:, 1] / z, K, terms, tilt)
        pixels[0, rows], pixels[1, rows] = u, v
        index[rows] = nearest_pixel_index(u, v, device.width, device.height)

    map_bands(project, chunks)
    buffer = np.full(device.height * device.width, np.inf)
    splat_nearest(buffer, index, depth)
    buffer = buffer.reshape(device.height, device.width)
    # the bilinear stencil's footprint, and the nearest pixel's alone (used where the first is mixed)
    stencils = []
    for stencil_px in (1.0, 0.0):
        reach = footprint_radius(thermal_blur_px, stencil_px)
        far = background_depth(buffer, reach, depth_tolerance_mm).ravel()
        stencils.append((far, SAMPLE_FOOTPRINTS + np.sqrt(2) * reach))
    guarded = None
    if unseen is not None:  # occluders for a second visibility test, not surfaces for the mixed-pixel test above
        u, v, z = image_coordinates(occluder_samples(unseen, device, depth_tolerance_mm), device)
        guarded = buffer.copy()
        splat_nearest(guarded.ravel(), nearest_pixel_index(u, v, device.width, device.height), z)
        guarded = fill_empty_pixels(guarded)
        guarded_nearest = nearest_depth_around(guarded, occlusion_margin_px).ravel() if occlusion_margin_px > 0 else None
        guarded = guarded.ravel()
    buffer = fill_empty_pixels(buffer)
    # the square window reaches margin * sqrt(2) pixels away along its diagonals
    guard_footprints = SAMPLE_FOOTPRINTS + np.sqrt(2) * occlusion_margin_px
    nearest = nearest_depth_around(buffer, occlusion_margin_px).ravel() if occlusion_margin_px > 0 else None
    surface = buffer.ravel()

    def sample(rows: slice) -> None:
        chunk_points, chunk_normals = points_of(rows), normals_of(rows)
        chunk_index, chunk_depth = index[rows], depth[rows]
        cosine = _view_cosines(chunk_points, chunk_normals, centre)
        angle = np.arccos(cosine)
        gradient = depth_gradient(rigid_transform(chunk_points, R, t), rigid_transform(chunk_normals, R, np.zeros(3)),
                                  focal, max_angle)
        tolerance = depth_tolerance(gradient, depth_tolerance_mm)
        seen = within_tolerance(chunk_index, chunk_depth, surface, tolerance)
        if nearest is not None:
            guard_tolerance = depth_tolerance(gradient, depth_tolerance_mm, guard_footprints)
            seen &= within_tolerance(chunk_index, chunk_depth, nearest, guard_tolerance)
        crossed = None
        if guarded is not None:  # seen past the cloud's points, but the thermal ray crosses a skirt
            crossed = seen & ~within_tolerance(chunk_index, chunk_depth, guarded, tolerance)
            if guarded_nearest is not None:
                crossed |= seen & ~within_tolerance(chunk_index, chunk_depth, guarded_nearest, guard_tolerance)
        # the footprint sees this surface alone: nothing farther (background, empty space) within its reach
        (bilinear_far, bilinear_footprints), (nearest_far, nearest_footprints) = stencils
        at = np.maximum(chunk_index, 0)
        reach = depth_tolerance(gradient, depth_tolerance_mm, bilinear_footprints)
        reach += chunk_depth
        bilinear_pure = bilinear_far[at] <= reach  # False for +inf (empty space within the footprint)
        pure = bilinear_pure.copy()
        edge = np.flatnonzero(seen & ~bilinear_pure)  # few: the band along depth edges
        pure[edge] = nearest_far[at[edge]] <= chunk_depth[edge] + depth_tolerance(gradient[edge], depth_tolerance_mm,
                                                                                  nearest_footprints)
        usable = np.flatnonzero(seen & pure & (angle <= max_angle))
        temperature = np.full(len(angle), np.nan)
        weight = np.zeros(len(angle))
        if len(usable):
            samples = _bilinear(view.frames, pixels[0, rows][usable], pixels[1, rows][usable], chunk_depth[usable],
                                buffer, tolerance[usable])
            alone = ~bilinear_pure[usable]
            if alone.any():  # the nearest pixel's footprint is pure where the stencil's is not
                nearest_values = view.frames.reshape(len(view.frames), -1)[:, chunk_index[usable[alone]]]
                # NaN stays NaN: a saturated corner on the point's own surface leaves it without a temperature
                samples[:, alone] = np.where(np.isfinite(samples[:, alone]), nearest_values, np.nan)
            if len(samples) == 1:
                frames_seen = np.isfinite(samples[0]).astype(np.float64)
                temperature[usable] = samples[0]
            else:
                finite = np.isfinite(samples)
                frames_seen = finite.sum(axis=0)
                mean = np.where(finite, samples, 0.0).sum(axis=0) / np.maximum(frames_seen, 1)
                temperature[usable] = np.where(frames_seen > 0, mean, np.nan)
            # cos(angle) (from before the arccos) times the pixels per mm^2 of surface at that distance
            offset = chunk_points[usable] - centre
            weight[usable] = cosine[usable] * frames_seen * focal**2 / np.einsum("ij,ij->i", offset, offset)
        angle[~seen] = np.nan
        result(rows, temperature, angle, weight, crossed)

    map_bands(sample, chunks)


def fuse_temperature(
    points: np.ndarray,
    normals: np.ndarray,
    views: Sequence[ThermalView],
    max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
    depth_tolerance_mm: float = DEFAULT_DEPTH_TOLERANCE_MM,
    occlusion_margin_px: int = DEFAULT_OCCLUSION_MARGIN_PX,
    thermal_blur_px: float = DEFAULT_THERMAL_BLUR_PX,
    unseen: UnseenSpace | None = None,
) -> TemperatureField:
    """Temperature of every cloud point from calibrated thermal views, fused by view angle and distance.

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
    thermal_blur_px : float
        The thermal optics' Gaussian blur, sigma in pixels: it sets the reach of
        the mixed-pixel test (:func:`services.fusion.visibility.footprint_radius`).
    unseen : UnseenSpace, optional
        The space the measuring camera(s) could not see into
        (:func:`services.fusion.carving.unseen_space`): its skirts are drawn
        into a second z-buffer of each view as occluders, so that a point whose
        thermal ray passes through space no device saw free gets no
        temperature from that view (``unguarded`` keeps the readings without
        this test, for :func:`services.fusion.carving.restore_consistent`).

    Returns
    -------
    TemperatureField
        ``temperature`` (N,) float32 degrees C and ``view_angle`` (N,) float32
        degrees (the smallest over the views that see the point past the
        cloud's points), NaN unseen; ``unguarded`` with ``unseen``.

    Notes
    -----
    Each point X projects to distorted pixel coordinates p = pi(K, dist, R X + t)
    in each thermal camera. It is seen if its depth z is within a tolerance of the
    z-buffer of the cloud at p (see :func:`services.fusion.visibility.splat_nearest`),
    so that a hidden point gets NaN rather than its occluder's temperature, and
    no surface nearer by more than the slope-scaled tolerance (over the
    window's reach) lies within the occlusion margin (a guard band at depth discontinuities [2]_).
    It gets a temperature only where its thermal footprint sees its surface alone:
    no z-buffer depth (and no empty pixel outside the cloud's outline) farther
    than its own depth plus the slope tolerance over the footprint's reach lies
    within r = ceil(1.5 + 2.5 sigma_blur) pixels of its nearest pixel
    (:func:`services.fusion.visibility.background_depth`); where that fails but
    holds within ceil(0.5 + 2.5 sigma_blur), the nearest pixel's value is used
    alone. A pixel on the part's silhouette mixes the part's radiance with the
    background's and reads a temperature of neither. Otherwise its
    temperature is the depth-aware bilinear sample at p, averaged over the
    view's frames, and views are fused by

        T = sum_v w_v T_v / sum_v w_v,   w_v = n_v cos(theta_v) (f_v / d_v)^2,

    with theta_v the angle between the normal and the line of sight, n_v the
    number of frames, f_v the view's focal length (pixels) and d_v its distance
    from the point (mm), for theta_v <= theta_max: the inverse of the surface
    area one pixel covers, (d_v / f_v)^2 / cos(theta_v), the view that resolves
    the point more finely counting more (a station's several thermal cameras see
    a point from different distances). The cosine also follows the fall of a
    surface's directional emissivity toward grazing angles [1]_.

    References
    ----------
    .. [1] M. Vollmer and K.-P. Moellmann, "Infrared Thermal Imaging", 2nd ed.,
       Wiley-VCH, 2018, sec. 1.4 (directional emissivity).
    .. [2] V. Lempitsky and D. Ivanov, "Seamless Mosaicing of Image-Based
       Texture Maps", CVPR 2007 (rejecting views near depth discontinuities).
    """
    if occlusion_margin_px < 0:
        raise ValueError(f"The occlusion margin must be a non-negative number of pixels; got {occlusion_margin_px}.")
    points, normals = _as_float(points), _as_float(normals)
    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points and normals must both be (N, 3); got {points.shape} and {normals.shape}.")
    return fuse_rows(len(points), rows_of(points), rows_of(normals), views, max_view_angle_deg, depth_tolerance_mm,
                     occlusion_margin_px, thermal_blur_px, unseen)


def fuse_rows(count: int, points_of: Rows, normals_of: Rows, views: Sequence[ThermalView],
              max_view_angle_deg: float = DEFAULT_MAX_VIEW_ANGLE_DEG,
              depth_tolerance_mm: float = DEFAULT_DEPTH_TOLERANCE_MM,
              occlusion_margin_px: int = DEFAULT_OCCLUSION_MARGIN_PX,
              thermal_blur_px: float = DEFAULT_THERMAL_BLUR_PX, unseen: UnseenSpace | None = None) -> TemperatureField:
    """:func:`fuse_temperature` of ``count`` points given chunk by chunk (e.g. stacked from a cloud's
    coordinate columns, without an (N, 3) copy of the whole cloud)."""
    if occlusion_margin_px < 0:
        raise ValueError(f"The occlusion margin must be a non-negative number of pixels; got {occlusion_margin_px}.")
    if not views:
        raise ValueError("At least one thermal view is needed to fuse a temperature field.")
    if not 0.0 < max_view_angle_deg < 90.0:
        raise ValueError(f"The view-angle limit must be in (0, 90) degrees; got {max_view_angle_deg}.")
    weighted_sum = np.zeros(count)
    weight_sum = np.zeros(count)
    best_angle = np.full(count, np.inf)
    # the same sums over the views whose rays cross no skirt of the unseen space
    guarded_sum = np.zeros(count) if unseen is not None else None
    guarded_weight = np.zeros(count) if unseen is not None else None

    def accumulate(rows: slice, temperature: np.ndarray, angle: np.ndarray, weight: np.ndarray,
                   crossed: np.ndarray | None) -> None:
        temperature *= weight
        contribution = np.where(weight > 0, temperature, 0.0)
        weighted_sum[rows] += contribution
        weight_sum[rows] += weight
        np.fmin(best_angle[rows], angle, out=best_angle[rows])
        if crossed is not None:
            guarded_sum[rows] += np.where(crossed, 0.0, contribution)
            guarded_weight[rows] += np.where(crossed, 0.0, weight)

    for view in views:
        _sample_view(count, points_of, normals_of, view, max_view_angle_deg, depth_tolerance_mm, occlusion_margin_px,
                     accumulate, thermal_blur_px, unseen)
    fused = np.empty(count, dtype=np.float32)
    fused_angle = np.empty(count, dtype=np.float32)
    guarded = np.empty(count, dtype=np.float32) if unseen is not None else None

    def finish(rows: slice) -> None:
        total = weight_sum[rows]
        with np.errstate(invalid="ignore", divide="ignore"):
            fused[rows] = np.where(total > 0, weighted_sum[rows] / total, np.nan)
            if guarded is not None:
                kept = guarded_weight[rows]
                guarded[rows] = np.where(kept > 0, guarded_sum[rows] / kept, np.nan)
        angle = best_angle[rows]
        angle[np.isinf(angle)] = np.nan
        fused_angle[rows] = np.rad2deg(angle)

    map_bands(finish, _chunks(count))
    if guarded is None:
        return TemperatureField(fused, fused_angle)
    return TemperatureField(guarded, fused_angle, unguarded=fused)
