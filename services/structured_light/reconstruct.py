"""From a decoded structured-light capture to a point cloud with per-point properties."""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.formats.sequence import Sequence
from services.geometry.camera_model import CameraModel
from services.geometry.cloud import PointCloud
from services.numba_options import SAFE_FASTMATH
from services.structured_light.decode import DecodedCapture, decode
from services.structured_light.glow import WINDOW_SIGMA_PX as GLOW_WINDOW_SIGMA_PX
from services.structured_light.glow import GlowReport, decode_glowing
from services.structured_light.low_snr import estimate_camera_noise, phase_noise_scale, refine_low_snr
from services.structured_light.outline import ASSUMED_CAMERA_BLUR_PX, estimate_camera_blur, outline_corrected
from services.structured_light.triangulate import TriangulationTable, triangulate_map, triangulation_table


def coded_axis(coded_axes: tuple[str, ...], camera: CameraModel, projector: CameraModel) -> str:
    """The projector axis to triangulate against: the coded one that best crosses the baseline.

    A coded projector column constrains depth when the camera-projector baseline runs across the
    columns (along projector x); a row when it runs along projector y.
    """
    available = list(coded_axes)
    if not available:
        raise ValueError("The capture codes neither projector axis, so nothing can be triangulated.")
    baseline = projector.R @ camera.centre + projector.t
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


def _refined_coordinates(decoded: DecodedCapture, sequence: Sequence, axis: str,
                         noise: np.ndarray | None = None) -> np.ndarray:
    """The decoded coordinates off the outline and corrected for the camera blur's bias beside it, with
    weak-signal pixels refined when the axis is phase coded (against the per-pixel ``noise`` when given,
    else the capture's one noise level)."""
    groups = sequence.phase_groups(axis)
    blur = estimate_camera_blur(decoded.intensity, decoded.rejection)
    coordinates = outline_corrected(getattr(decoded, f"projector_{axis}"), decoded.intensity, decoded.rejection,
                                    groups[-1].period if groups else None,
                                    ASSUMED_CAMERA_BLUR_PX if blur is None else blur)
    if not groups or len(groups[-1].frames) <= 3 or not np.isfinite(coordinates).any():
        return coordinates
    finest = groups[-1]
    steps = len(finest.frames)
    if noise is not None:  # the predicted noise scale / B per pixel is then scale(1) / (B / noise)
        return refine_low_snr(coordinates, decoded.modulation / noise, phase_noise_scale(steps, finest.period, 1.0),
                              max_step=finest.period / 4)
    noise_level = estimate_camera_noise(decoded.modulation, decoded.quality, steps)
    return refine_low_snr(coordinates, decoded.modulation, phase_noise_scale(steps, finest.period, noise_level),
                          max_step=finest.period / 4)


# Hand-written with numba: OpenCV's filterSpeckles is the same flood fill, but serial and on 16-bit
# integers; here it runs on the float coordinates in horizontal bands, one per thread.
@numba.njit(cache=True)
def _band_speckles(coordinates, top, bottom, first, last, max_step, max_speckle_px, out):
    """Flood-fill rows top..bottom of the coordinates and write rows first..last of ``out``, NaN on the
    regions of at most ``max_speckle_px`` pixels."""
    width = coordinates.shape[1]
    values = coordinates[top:bottom].ravel()
    n = values.size
    labels = np.zeros(n, np.int32)
    region_size = np.empty(n + 1, np.int32)  # room for the most regions: an array grown in the loop costs 5x
    stack = np.empty(n, np.int32)  # flat indices of the pixels to visit, and their columns
    stack_col = np.empty(n, np.int32)
    regions = 0
    for row in range(first, last):
        for col in range(width):
            seed = (row - top) * width + col
            value = values[seed]
            out[row, col] = value
            if not np.isfinite(value):
                continue
            label = labels[seed]
            if label == 0:
                regions += 1
                label = regions
                labels[seed], stack[0], stack_col[0] = label, seed, col
                depth, size = 1, 0
                while depth > 0:
                    depth -= 1
                    p, c = stack[depth], stack_col[depth]
                    size += 1
                    here = values[p]
                    # the four neighbours, joined where their coordinates differ by at most max_step (not NaN)
                    q = p - width
                    if p >= width and labels[q] == 0 and abs(values[q] - here) <= max_step:
                        labels[q], stack[depth], stack_col[depth] = label, q, c
                        depth += 1
                    q = p + width
                    if q < n and labels[q] == 0 and abs(values[q] - here) <= max_step:
                        labels[q], stack[depth], stack_col[depth] = label, q, c
                        depth += 1
                    q = p - 1
                    if c > 0 and labels[q] == 0 and abs(values[q] - here) <= max_step:
                        labels[q], stack[depth], stack_col[depth] = label, q, c - 1
                        depth += 1
                    q = p + 1
                    if c + 1 < width and labels[q] == 0 and abs(values[q] - here) <= max_step:
                        labels[q], stack[depth], stack_col[depth] = label, q, c + 1
                        depth += 1
                region_size[label] = size
            if region_size[label] <= max_speckle_px:
                out[row, col] = np.nan


@numba.njit(parallel=True, cache=True)
def _speckles_kernel(coordinates, bands, max_step, max_speckle_px, out):
    height = coordinates.shape[0]
    for band in numba.prange(bands):
        first, last = band * height // bands, (band + 1) * height // bands
        _band_speckles(coordinates, max(0, first - max_speckle_px), min(height, last + max_speckle_px),
                       first, last, max_step, max_speckle_px, out)


def remove_speckles(coordinates: np.ndarray, max_step: float, max_speckle_px: int = 25) -> np.ndarray:
    """Reject small islands of decoded pixels that disagree with everything around them.

    Parameters
    ----------
    coordinates : (H, W) float32 array
        Decoded projector coordinates, NaN where invalid.
    max_step : float
        Largest coordinate difference, in projector pixels, between 4-neighbours of one surface.
    max_speckle_px : int
        Connected regions of at most this many pixels are removed.

    Returns
    -------
    coordinates : (H, W) float32 array
        The coordinates, NaN on the removed islands.

    Notes
    -----
    Pixels are grouped by 4-connected flood fill where neighbours differ by at most ``max_step``; a
    decoding error (a misread high Gray bit, an unwrapping slip) produces an island that differs from its
    surroundings by at least a period and is removed, like OpenCV's speckle filter for disparity maps
    (``filterSpeckles``) [1]_. The image is filled in horizontal bands in parallel, each with
    ``max_speckle_px`` rows of context on either side, which gives exactly the whole image's result: a
    speckle spans at most that many rows, so it lies whole within the context of any band it touches, and a
    larger region that leaves the context spans more rows than that inside it.

    References
    ----------
    .. [1] H. Hirschmuller, "Stereo processing by semiglobal matching and mutual information",
       IEEE TPAMI 30(2), 2008 (the speckle filter of OpenCV's ``filterSpeckles``).
    """
    coordinates = np.ascontiguousarray(coordinates, dtype=np.float32)
    if coordinates.ndim != 2:
        raise ValueError(f"The coordinates must be an (H, W) image; got an array of shape {coordinates.shape}.")
    if max_speckle_px < 1:
        raise ValueError(f"max_speckle_px must be at least 1 pixel; got {max_speckle_px}.")
    kept = np.empty_like(coordinates)
    bands = min(numba.get_num_threads(), coordinates.shape[0] // (4 * max_speckle_px) + 1)
    _speckles_kernel(coordinates, bands, float(max_step), int(max_speckle_px), kept)
    return kept


# Hand-written with numba: normals are needed only at the valid pixels, and numpy's cross products over
# the whole map cost several times more.
@numba.njit(cache=True, inline="always")
def _normal_at(points_map, row, col, camera_centre, out):
    """Central-difference normal at one pixel of an organised point map, facing the camera; NaN when a
    neighbour is missing or the pixel is on the border."""
    height, width = points_map.shape[:2]
    out[0] = out[1] = out[2] = np.nan
    if row == 0 or col == 0 or row == height - 1 or col == width - 1:
        return
    ax = points_map[row, col + 1, 0] - points_map[row, col - 1, 0]
    ay = points_map[row, col + 1, 1] - points_map[row, col - 1, 1]
    az = points_map[row, col + 1, 2] - points_map[row, col - 1, 2]
    bx = points_map[row + 1, col, 0] - points_map[row - 1, col, 0]
    by = points_map[row + 1, col, 1] - points_map[row - 1, col, 1]
    bz = points_map[row + 1, col, 2] - points_map[row - 1, col, 2]
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    if not norm > 0.0:  # also NaN: a neighbour is missing
        return
    facing = (nx * (camera_centre[0] - points_map[row, col, 0]) + ny * (camera_centre[1] - points_map[row, col, 1])
              + nz * (camera_centre[2] - points_map[row, col, 2]))
    scale = (1.0 if facing >= 0 else -1.0) / norm
    out[0], out[1], out[2] = scale * nx, scale * ny, scale * nz


@numba.njit(parallel=True, cache=True, fastmath=SAFE_FASTMATH)
def _normals_kernel(points_map, camera_centre, out):
    for row in numba.prange(points_map.shape[0]):
        for col in range(points_map.shape[1]):
            _normal_at(points_map, row, col, camera_centre, out[row, col])


def surface_normals(points_map: np.ndarray, camera_centre: np.ndarray) -> np.ndarray:
    """Unit normals of an organised point map from central differences, facing the camera.

    Parameters
    ----------
    points_map : (H, W, 3) array
        World points per camera pixel, NaN where there is none.
    camera_centre : (3,) array
        Camera centre in world coordinates, used to orient the normals.

    Returns
    -------
    normals : (H, W, 3) float32 array
        NaN where a neighbour is missing.

    Notes
    -----
    n = (P(u+1, v) - P(u-1, v)) x (P(u, v+1) - P(u, v-1)), normalised and flipped so that
    n . (C - P) > 0.
    """
    normals = np.empty(points_map.shape, dtype=np.float32)
    _normals_kernel(np.ascontiguousarray(points_map, dtype=np.float32), np.asarray(camera_centre, np.float64),
                    normals)
    return normals


_CLOUD_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "u", "v", "projector", "quality", "modulation", "intensity")


# Hand-written with numba: the cloud is gathered from the maps in one parallel pass, each row written
# from its offset, where numpy would gather twelve arrays one by one through an index array.
@numba.njit(parallel=True, cache=True, fastmath=SAFE_FASTMATH)
def _row_point_counts(points_map, counts):
    for row in numba.prange(points_map.shape[0]):
        n = 0
        for col in range(points_map.shape[1]):
            n += np.isfinite(points_map[row, col, 0])
        counts[row] = n


@numba.njit(parallel=True, cache=True, fastmath=SAFE_FASTMATH)
def _cloud_kernel(points_map, row_starts, camera_centre, coordinates, quality, modulation, intensity, out):
    for row in numba.prange(points_map.shape[0]):
        i = row_starts[row]
        normal = np.empty(3, dtype=np.float32)
        for col in range(points_map.shape[1]):
            if not np.isfinite(points_map[row, col, 0]):
                continue
            _normal_at(points_map, row, col, camera_centre, normal)
            out[0, i], out[1, i], out[2, i] = points_map[row, col, 0], points_map[row, col, 1], points_map[row, col, 2]
            out[3, i], out[4, i], out[5, i] = normal[0], normal[1], normal[2]
            out[6, i], out[7, i] = col, row
            out[8, i], out[9, i] = coordinates[row, col], quality[row, col]
            out[10, i], out[11, i] = modulation[row, col], intensity[row, col]
            i += 1


def _cloud(points_map: np.ndarray, camera_centre: np.ndarray, coordinates: np.ndarray,
           decoded: DecodedCapture) -> PointCloud:
    """The reconstructed pixels of the point map with their normals and decoding properties, in raster order."""
    counts = np.empty(points_map.shape[0], dtype=np.int64)
    _row_point_counts(points_map, counts)
    row_starts = np.concatenate([[0], np.cumsum(counts)])
    columns = np.empty((len(_CLOUD_FIELDS), row_starts[-1]), dtype=np.float32)
    _cloud_kernel(points_map, row_starts, camera_centre, coordinates, decoded.quality, decoded.modulation,
                  decoded.intensity, columns)
    return PointCloud(dict(zip(_CLOUD_FIELDS, columns, strict=True)))


@dataclass(frozen=True)
class Reconstruction:
    """A reconstructed capture: the ``cloud`` (see :func:`reconstruct_points`) and, for a capture of a
    glowing part (a sequence closed by a second black frame), what the glow did (``glow``), else None."""

    cloud: PointCloud
    glow: GlowReport | None


def reconstruct_scan(
    frames: np.ndarray,
    sequence: Sequence,
    camera: CameraModel,
    projector: CameraModel,
    *,
    table: TriangulationTable | None = None,
    gray_boundaries: bool = True,
    saturation_level: float | None = None,
    max_indirect: float = np.inf,
    consistency: float = 0.25,
    glow_window_px: float = GLOW_WINDOW_SIGMA_PX,
) -> Reconstruction:
    """Decode a capture and triangulate every valid camera pixel, reporting what a hot part's glow did.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        Camera frames in the manifest's display order.
    sequence : Sequence
        What each frame encodes. A sequence that opens and closes with a black frame (our hot-part
        sequences) is decoded by ``glow.decode_glowing``: the drifting glow is interpolated between the
        two and subtracted, and the thresholds follow the noise measured per pixel.
    camera, projector : CameraModel
        Calibrated devices of the rig.
    table : TriangulationTable, optional
        :func:`~services.structured_light.triangulate.triangulation_table` of the devices for the
        sequence's coded axis, to reuse across scans of one calibration; computed here when None.
    gray_boundaries : bool
        Interpolate axes coded by Gray code alone between their stripe boundaries (``decode``'s option);
        False triangulates their stripe centres.
    saturation_level : float, optional
        The sensor's saturation grey level (4095 for 12-bit frames in 16-bit files); default the
        dtype maximum.
    max_indirect : float
        Reject pixels whose indirect light (inter-reflections) exceeds this multiple of their direct
        light, estimated from the fringe visibility (``decode``'s ``INDIRECT``); off by default,
        since ambient light and a hot part's glow lower the visibility too.
    consistency : float
        ``decode``'s tolerance of a Gray code or coarser period against the unwrapped phase, as a
        fraction of the unwrapping margin. Raise it (e.g. to 0.5) for sequences unwrapped by a much
        coarser period with few steps, whose coarse phase is noisy (SLStudio's 3 steps at 16
        periods): unwrapping slips then leave islands a period off, which the speckle filter removes.
    glow_window_px : float
        ``decode_glowing``'s window (Gaussian sigma, px) over which pixels lost to the glow's noise
        are decoded again; 0 turns that off.

    Returns
    -------
    Reconstruction
    """
    height, width = frames.shape[1:]
    if (width, height) != camera.size:
        raise ValueError(
            f"The frames are {width}x{height} but the camera is calibrated for {camera.width}x{camera.height}."
        )
    axis = coded_axis(sequence.coded_axes, camera, projector)
    if table is None:
        table = triangulation_table(camera, projector, axis)
    elif table.axis != axis or table.pixel_geometry.shape[:2] != (height, width):
        raise ValueError(f"The triangulation table is for projector {table.axis} and a "
                         f"{table.pixel_geometry.shape[1]}x{table.pixel_geometry.shape[0]} camera, "
                         "not for this capture.")
    full_scale = float(np.iinfo(frames.dtype).max if saturation_level is None else saturation_level)
    noise, report = None, None
    if sequence.closing_black_index is not None and sequence.phase_groups():
        decoded, noise, report = decode_glowing(frames, sequence, saturation_level=full_scale,
                                                min_quality=_MIN_QUALITY, window_sigma_px=glow_window_px)
    else:
        decoded = decode(frames, sequence, min_quality=_MIN_QUALITY, edge_margin=0, saturation_level=full_scale,
                         min_modulation=_MIN_MODULATION_OF_FULL_SCALE * full_scale, gray_boundaries=gray_boundaries,
                         max_indirect=max_indirect, consistency=consistency)
    coordinates = _refined_coordinates(decoded, sequence, axis, noise)
    coordinates = remove_speckles(coordinates, _coordinate_step_limit(sequence, axis))
    points_map = triangulate_map(table, coordinates)
    return Reconstruction(cloud=_cloud(points_map, table.centre_world, coordinates, decoded), glow=report)


def reconstruct_points(
    frames: np.ndarray,
    sequence: Sequence,
    camera: CameraModel,
    projector: CameraModel,
    *,
    table: TriangulationTable | None = None,
    gray_boundaries: bool = True,
    saturation_level: float | None = None,
    max_indirect: float = np.inf,
    consistency: float = 0.25,
) -> PointCloud:
    """Decode a capture and triangulate every valid camera pixel.

    Parameters
    ----------
    frames : (F, H, W) uint8 or uint16 array
        Camera frames in the manifest's display order.
    sequence : Sequence
        What each frame encodes.
    camera, projector : CameraModel
        Calibrated devices of the rig.
    table : TriangulationTable, optional
        :func:`~services.structured_light.triangulate.triangulation_table` of the devices for the
        sequence's coded axis, to reuse across scans of one calibration; computed here when None.
    gray_boundaries : bool
        Interpolate axes coded by Gray code alone between their stripe boundaries (``decode``'s option);
        False triangulates their stripe centres.
    saturation_level : float, optional
        The sensor's saturation grey level; default the dtype maximum.
    max_indirect : float
        Reject pixels whose indirect light (inter-reflections) exceeds this multiple of their direct
        light, estimated from the fringe visibility (``decode``'s ``INDIRECT``); off by default,
        since ambient light and a hot part's glow lower the visibility too.
    consistency : float
        ``decode``'s tolerance of a Gray code or coarser period against the unwrapped phase, as a
        fraction of the unwrapping margin. Raise it (e.g. to 0.5) for sequences unwrapped by a much
        coarser period with few steps, whose coarse phase is noisy (SLStudio's 3 steps at 16
        periods): unwrapping slips then leave islands a period off, which the speckle filter removes.

    Returns
    -------
    cloud : PointCloud
        ``x, y, z`` (float32 world mm), ``nx, ny, nz`` (unit normals, NaN at the cloud's border),
        ``u, v`` (camera pixel, float32), ``projector`` (decoded projector coordinate),
        ``quality``, ``modulation``, ``intensity`` (float32), one entry per reconstructed point, in
        camera raster order. :func:`reconstruct_scan` also says what a hot part's glow did.
    """
    return reconstruct_scan(frames, sequence, camera, projector, table=table, gray_boundaries=gray_boundaries,
                            saturation_level=saturation_level, max_indirect=max_indirect,
                            consistency=consistency).cloud
