"""From a decoded structured-light capture to a point cloud with per-point properties."""

from __future__ import annotations

import cv2
import numba
import numpy as np

from services.formats.rig import Device
from services.formats.sequence import Sequence
from services.structured_light.decode import DecodedCapture, Rejection, decode
from services.structured_light.low_snr import estimate_camera_noise, phase_noise_scale, refine_low_snr
from services.structured_light.triangulate import camera_ray_table, triangulate


def coded_axis(decoded: DecodedCapture, camera: Device, projector: Device) -> str:
    """The projector axis to triangulate against: the coded one that best crosses the baseline.

    A coded projector column constrains depth when the camera-projector baseline runs across the
    columns (along projector x); a row when it runs along projector y.
    """
    available = list(decoded.coded_axes)
    if not available:
        raise ValueError("The capture codes neither projector axis, so nothing can be triangulated.")
    camera_centre = -camera.R_array.T @ camera.t_array
    baseline = projector.R_array @ camera_centre + projector.t_array
    return max(available, key=lambda axis: abs(baseline[0 if axis == "x" else 1]))


def _coordinate_step_limit(sequence: Sequence, axis: str) -> float:
    """Largest plausible coordinate change between neighbouring pixels: half the finest period, or
    four stripes of a Gray-code-only axis. Decoding errors (a misread Gray bit, a wrong period) jump by
    at least a whole period or stripe group."""
    groups = sequence.phase_groups(axis)
    if groups:
        return min(group.period for group in groups) / 2
    return 4.0 * (1 << sequence.gray_planes(axis)[0].bit)


# Decoding thresholds for reconstruction: weak signals (grazing light) are kept and refined by
# ``refine_low_snr`` instead of rejected; the outline margin is seeded only where there is no signal.
_MIN_QUALITY = 0.3
_MIN_MODULATION_OF_FULL_SCALE = 0.004  # 1 grey level at 8 bits
_OUTLINE_MARGIN_PX = 3  # about four times the camera blur sigma
_OUTLINE_RAMP = 0.9


def _outline_margin(decoded: DecodedCapture) -> np.ndarray:
    """Pixels whose blur footprint reaches past the object's outline (as the camera sees it), or a deep
    shadow or saturation: the neighbours of a pixel without signal, and the pixels within
    ``_OUTLINE_MARGIN_PX`` of one whose brightness is still pulled down by the dark side (below
    ``_OUTLINE_RAMP`` of the brightest pixel around). Mixing with the dark side biases the phase."""
    no_signal = ((decoded.rejection == Rejection.DARK) | (decoded.rejection == Rejection.SATURATED)).astype(np.uint8)
    neighbours = cv2.dilate(no_signal, np.ones((3, 3), np.uint8)).astype(bool)
    window = 2 * _OUTLINE_MARGIN_PX + 1
    near = cv2.dilate(no_signal, np.ones((window, window), np.uint8)).astype(bool)
    intensity = np.nan_to_num(decoded.intensity.astype(np.float32))
    ramp = intensity < _OUTLINE_RAMP * cv2.dilate(intensity, np.ones((window, window), np.uint8))
    return neighbours | (near & ramp)


def _refined_coordinates(decoded: DecodedCapture, sequence: Sequence, axis: str) -> np.ndarray:
    """The decoded coordinates off the outline, with weak-signal pixels refined when the axis is phase coded."""
    coordinates = np.where(_outline_margin(decoded), np.float32(np.nan),
                           getattr(decoded, f"projector_{axis}"))
    groups = sequence.phase_groups(axis)
    if not groups or len(groups[-1].frames) <= 3 or not np.isfinite(coordinates).any():
        return coordinates
    finest = groups[-1]
    steps = len(finest.frames)
    noise = estimate_camera_noise(decoded.modulation, decoded.quality, steps)
    return refine_low_snr(coordinates, decoded.modulation, phase_noise_scale(steps, finest.period, noise),
                          max_step=finest.period / 4)


def remove_speckles(coordinates: np.ndarray, axis_size: int, max_step: float, max_speckle_px: int = 25) -> np.ndarray:
    """Reject small islands of decoded pixels that disagree with everything around them.

    Parameters
    ----------
    coordinates : (H, W) float array
        Decoded projector coordinates, NaN where invalid.
    axis_size : int
        Projector pixels along the coded axis.
    max_step : float
        Largest coordinate difference, in projector pixels, between 4-neighbours of one surface.
    max_speckle_px : int
        Connected regions of at most this many pixels are removed.

    Returns
    -------
    keep : (H, W) bool array
        Valid pixels that belong to a region larger than ``max_speckle_px``.

    Notes
    -----
    Pixels are grouped by 4-connected flood fill where neighbours differ by at most ``max_step``; a
    decoding error (a misread high Gray bit, an unwrapping slip) produces an island that differs from its
    surroundings by at least a period and is removed, like OpenCV's speckle filter for disparity maps,
    which this calls on the coordinates quantised to 16-bit integers.

    References
    ----------
    .. [1] H. Hirschmuller, "Stereo processing by semiglobal matching and mutual information",
       IEEE TPAMI 30(2), 2008 (the speckle filter of OpenCV's ``filterSpeckles``).
    """
    invalid = np.int16(-32768)
    scale = 32000.0 / (axis_size + 1)
    valid = np.isfinite(coordinates)
    quantised = np.full(coordinates.shape, invalid, dtype=np.int16)
    quantised[valid] = np.rint((coordinates[valid] + 0.5) * scale).astype(np.int16)
    cv2.filterSpeckles(quantised, int(invalid), max_speckle_px, max(1, int(max_step * scale)))
    return quantised != invalid


# Hand-written with numba: normals are needed only at the valid pixels, and numpy's cross products over
# the whole map cost ten times more.
@numba.njit(parallel=True, cache=True)
def _normals_kernel(points_map, camera_centre, flat_index, out):
    height, width = points_map.shape[:2]
    for i in numba.prange(flat_index.shape[0]):
        row, col = flat_index[i] // width, flat_index[i] % width
        out[i, 0] = out[i, 1] = out[i, 2] = np.nan
        if row == 0 or col == 0 or row == height - 1 or col == width - 1:
            continue
        ax = points_map[row, col + 1, 0] - points_map[row, col - 1, 0]
        ay = points_map[row, col + 1, 1] - points_map[row, col - 1, 1]
        az = points_map[row, col + 1, 2] - points_map[row, col - 1, 2]
        bx = points_map[row + 1, col, 0] - points_map[row - 1, col, 0]
        by = points_map[row + 1, col, 1] - points_map[row - 1, col, 1]
        bz = points_map[row + 1, col, 2] - points_map[row - 1, col, 2]
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        if not norm > 0.0:  # also NaN: a neighbour is missing
            continue
        facing = (nx * (camera_centre[0] - points_map[row, col, 0]) + ny * (camera_centre[1] - points_map[row, col, 1])
                  + nz * (camera_centre[2] - points_map[row, col, 2]))
        sign = 1.0 if facing >= 0 else -1.0
        out[i, 0], out[i, 1], out[i, 2] = sign * nx / norm, sign * ny / norm, sign * nz / norm


def surface_normals(points_map: np.ndarray, camera_centre: np.ndarray, flat_index: np.ndarray | None = None) -> np.ndarray:
    """Unit normals of an organised point map from central differences, facing the camera.

    Parameters
    ----------
    points_map : (H, W, 3) array
        World points per camera pixel, NaN where there is none.
    camera_centre : (3,) array
        Camera centre in world coordinates, used to orient the normals.
    flat_index : (N,) int array, optional
        Raster indices of the pixels wanted; all pixels when None.

    Returns
    -------
    normals : (N, 3) float32 array, or (H, W, 3) when ``flat_index`` is None
        NaN where a neighbour is missing.

    Notes
    -----
    n = (P(u+1, v) - P(u-1, v)) x (P(u, v+1) - P(u, v-1)), normalised and flipped so that
    n . (C - P) > 0.
    """
    height, width = points_map.shape[:2]
    wanted = np.arange(height * width) if flat_index is None else np.asarray(flat_index)
    normals = np.empty((len(wanted), 3), dtype=np.float32)
    _normals_kernel(np.ascontiguousarray(points_map, dtype=np.float32), np.asarray(camera_centre, np.float64),
                    wanted.astype(np.int64), normals)
    return normals if flat_index is not None else normals.reshape(height, width, 3)


def reconstruct_points(
    frames: np.ndarray,
    sequence: Sequence,
    camera: Device,
    projector: Device,
    *,
    rays: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Decode a capture and triangulate every valid camera pixel.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        Camera frames in the manifest's display order.
    sequence : Sequence
        What each frame encodes.
    camera, projector : Device
        Calibrated devices of the rig.
    rays : (H, W, 2) array, optional
        :func:`camera_ray_table` of the camera, to reuse across scans of one calibration.

    Returns
    -------
    cloud : dict of 1-D arrays
        ``x, y, z`` (float32 world mm), ``nx, ny, nz`` (unit normals, NaN at the cloud's border),
        ``u, v`` (camera pixel, float32), ``projector`` (decoded projector coordinate),
        ``quality``, ``modulation``, ``intensity`` (float32), one entry per reconstructed point, in
        camera raster order.
    """
    height, width = frames.shape[1:]
    if (width, height) != camera.size:
        raise ValueError(
            f"The frames are {width}x{height} but the camera is calibrated for {camera.width}x{camera.height}."
        )
    if rays is None:
        rays = camera_ray_table(camera.K_array, camera.dist_array, width, height)
    full_scale = np.iinfo(frames.dtype).max
    decoded = decode(frames, sequence, min_quality=_MIN_QUALITY, edge_margin=0,
                     min_modulation=_MIN_MODULATION_OF_FULL_SCALE * full_scale)
    axis = coded_axis(decoded, camera, projector)
    coordinates = _refined_coordinates(decoded, sequence, axis)
    valid = remove_speckles(coordinates, sequence.axis_size(axis), _coordinate_step_limit(sequence, axis))
    flat_index = np.flatnonzero(valid)
    points = triangulate(rays.reshape(-1, 2)[flat_index], coordinates.ravel()[flat_index], axis,
                         camera.R_array, camera.t_array, projector.K_array, projector.dist_array,
                         projector.R_array, projector.t_array)
    met = np.isfinite(points[:, 0])
    flat_index, points = flat_index[met], points[met]

    points_map = np.full((height, width, 3), np.nan, dtype=np.float32)
    points_map.reshape(-1, 3)[flat_index] = points
    normals = surface_normals(points_map, -camera.R_array.T @ camera.t_array, flat_index)
    v, u = np.divmod(flat_index, width)
    return {
        "x": points[:, 0], "y": points[:, 1], "z": points[:, 2],
        "nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2],
        "u": u.astype(np.float32), "v": v.astype(np.float32),
        "projector": coordinates.ravel()[flat_index].astype(np.float32),
        "quality": decoded.quality.ravel()[flat_index].astype(np.float32),
        "modulation": decoded.modulation.ravel()[flat_index].astype(np.float32),
        "intensity": decoded.intensity.ravel()[flat_index].astype(np.float32),
    }
