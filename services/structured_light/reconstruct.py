"""From a decoded structured-light capture to a point cloud with per-point properties."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.formats.sequence import Sequence
from services.geometry.camera_model import CameraModel
from services.geometry.cloud import PointCloud
from services.structured_light.decode import DecodedCapture, decode
from services.structured_light.glow import WINDOW_SIGMA_PX as GLOW_WINDOW_SIGMA_PX
from services.structured_light.glow import GlowReport, decode_glowing
from services.structured_light.low_snr import estimate_camera_noise, phase_noise_scale, refine_low_snr
from services.structured_light.outline import ASSUMED_CAMERA_BLUR_PX, estimate_camera_blur, outline_corrected
from services.structured_light.row_bands import map_bands, thread_count
from services.structured_light.triangulate import TriangulationTable, triangulate_map, triangulation_table
from services.structured_light import defaults


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
# ``refine_low_snr`` instead of rejected; the outline margins are seeded only where there is no signal, or no
# pattern (``outline_corrected``).
_MIN_QUALITY = 0.3
_MIN_MODULATION_OF_FULL_SCALE = 0.004  # 1 grey level at 8 bits
# 4-neighbours whose coordinates differ by more than this many finest periods are both EDGE: a depth step,
# where a pixel straddling the silhouette mixes two surfaces' fringes. One period keeps the steep field beside
# a sphere's limb (half a period cost 0.7 % of the paper sphere) and drops the mixed pixels of issue 34's
# tuning scene (docs/structured-light.md, "Points at projector shadows and depth steps").
_JUMP_OF_PERIOD = 1.0


def _refined_coordinates(decoded: DecodedCapture, sequence: Sequence, axis: str,
                         noise: np.ndarray | None = None, gray_boundaries: bool = True) -> np.ndarray:
    """The decoded coordinates off the outline and corrected for the camera blur's bias beside it, with
    weak-signal pixels refined when the axis is phase coded (against the per-pixel ``noise`` when given,
    else the capture's one noise level)."""
    groups = sequence.phase_groups(axis)
    blur = estimate_camera_blur(decoded.intensity, decoded.rejection)
    # Gray-code-only coordinates interpolated between stripe boundaries are biased beside the outline like a
    # phase; the finest Gray plane, four stripes long, then plays the finest period's part.
    interpolated = not groups and gray_boundaries and bool(sequence.gray_planes(axis))
    period = groups[-1].period if groups else float(4 << sequence.gray_planes(axis)[0].bit) if interpolated else None
    coordinates = outline_corrected(getattr(decoded, f"projector_{axis}"), decoded.intensity, decoded.rejection,
                                    period, ASSUMED_CAMERA_BLUR_PX if blur is None else blur,
                                    modulation=decoded.modulation, boundaries=interpolated)
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


def _speckle_mask(coordinates: np.ndarray, max_step: float, max_speckle_px: int) -> np.ndarray:
    """Where the coordinates lie in regions of at most ``max_speckle_px`` pixels.

    OpenCV labels the regions (its ``filterSpeckles`` does the same flood fill, but on 16-bit integers):
    on a grid of twice the resolution whose even cells are the pixels and whose cells between two pixels
    are set where these join, 4-connected components are the regions.
    """
    height, width = coordinates.shape
    graph = np.zeros((2 * height - 1, 2 * width - 1), np.uint8)
    graph[::2, ::2] = np.isfinite(coordinates)
    with np.errstate(invalid="ignore"):  # NaN never joins
        graph[::2, 1::2] = np.abs(np.diff(coordinates, axis=1)) <= max_step
        graph[1::2, ::2] = np.abs(np.diff(coordinates, axis=0)) <= max_step
    count, labels = cv2.connectedComponentsWithAlgorithm(graph, 4, cv2.CV_32S, cv2.CCL_BOLELLI)
    pixel_labels = labels[::2, ::2]
    speckles = np.bincount(pixel_labels.ravel(), minlength=count) <= max_speckle_px
    speckles[0] = False  # the background: NaN already
    return speckles[pixel_labels]


def _speckles_in_bands(coordinates: np.ndarray, bands: int, max_step: float, max_speckle_px: int,
                       out: np.ndarray) -> None:
    """:func:`remove_speckles` into ``out``, the image labelled in ``bands`` bands of rows on the thread
    pool, each with ``max_speckle_px`` rows of context on either side."""
    height = coordinates.shape[0]

    def band_without_speckles(rows: slice) -> None:
        top, bottom = max(0, rows.start - max_speckle_px), min(height, rows.stop + max_speckle_px)
        speckles = _speckle_mask(coordinates[top:bottom], max_step, max_speckle_px)
        out[rows] = np.where(speckles[rows.start - top:rows.stop - top], np.float32(np.nan), coordinates[rows])

    map_bands(band_without_speckles,
              [slice(band * height // bands, (band + 1) * height // bands) for band in range(bands)])


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
    (``filterSpeckles``) [1]_, here labelled by OpenCV's connected components on a grid that holds the
    pixels and the joins between them. The image is labelled in horizontal bands in parallel, each with
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
    bands = min(thread_count(), coordinates.shape[0] // (4 * max_speckle_px) + 1)
    _speckles_in_bands(coordinates, bands, float(max_step), int(max_speckle_px), kept)
    return kept


def _normals_at(points: np.ndarray, width: int, pixels: np.ndarray, row: np.ndarray, col: np.ndarray,
                centre: np.ndarray, camera_centre: np.ndarray, out: np.ndarray) -> None:
    """Normals (see :func:`surface_normals`) into the (3, N) ``out`` at flat pixel indices ``pixels`` (at
    ``row``, ``col``, points ``centre``) of the flat (H * W, 3) point map ``points``: gathers of the four
    neighbours, where slices of the whole map would compute normals for every pixel, decoded or not."""
    last = len(points) - 1
    a = np.take(points, np.minimum(pixels + 1, last), axis=0)  # the border's neighbours are clipped or
    a -= np.take(points, np.maximum(pixels - 1, 0), axis=0)  # wrapped; their normals are NaN below
    b = np.take(points, np.minimum(pixels + width, last), axis=0)
    b -= np.take(points, np.maximum(pixels - width, 0), axis=0)
    (ax, ay, az), (bx, by, bz) = a.T, b.T
    nx, ny, nz = out
    np.multiply(ay, bz, out=nx)
    nx -= az * by
    np.multiply(az, bx, out=ny)
    ny -= ax * bz
    np.multiply(ax, by, out=nz)
    nz -= ay * bx
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    # n . (C - P), per column: numpy broadcasts over rows of three slowly
    facing = sum(n * (np.float32(c) - p) for n, c, p in zip(out, camera_centre, centre.T, strict=True))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(facing >= 0, np.float32(1.0), np.float32(-1.0)) / norm
    height = len(points) // width
    scale[(row == 0) | (row == height - 1) | (col == 0) | (col == width - 1) | ~(norm > 0.0)] = np.nan
    out *= scale  # NaN also where a neighbour is missing


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
    points = np.ascontiguousarray(points_map, dtype=np.float32).reshape(-1, 3)
    height, width = points_map.shape[:2]
    pixels = np.arange(height * width)
    normals = np.empty((3, len(pixels)), dtype=np.float32)
    _normals_at(points, width, pixels, *np.divmod(pixels, width), points, camera_centre, normals)
    return np.ascontiguousarray(normals.T).reshape(points_map.shape)


_CLOUD_FIELDS = ("x", "y", "z", "nx", "ny", "nz", "u", "v", "projector", "quality", "modulation", "intensity")
_CLOUD_CHUNK_POINTS = 1 << 16  # points gathered per task on the thread pool


def _cloud(points_map: np.ndarray, camera_centre: np.ndarray, coordinates: np.ndarray,
           decoded: DecodedCapture) -> PointCloud:
    """The reconstructed pixels of the point map with their normals and decoding properties, in raster order."""
    height, width = points_map.shape[:2]
    points = points_map.reshape(-1, 3)
    pixels = np.flatnonzero(np.isfinite(points[:, 0]))
    columns = np.empty((len(_CLOUD_FIELDS), len(pixels)), dtype=np.float32)
    properties = [np.ascontiguousarray(image, dtype=np.float32).reshape(-1)
                  for image in (coordinates, decoded.quality, decoded.modulation, decoded.intensity)]

    def gather_chunk(chunk: slice) -> None:
        here = pixels[chunk]
        centre = np.take(points, here, axis=0)
        columns[0:3, chunk] = centre.T
        v, u = np.divmod(here, width)
        _normals_at(points, width, here, v, u, centre, camera_centre, columns[3:6, chunk])
        columns[6, chunk], columns[7, chunk] = u, v
        for row, image in enumerate(properties, start=8):
            columns[row, chunk] = np.take(image, here)

    map_bands(gather_chunk, [slice(first, first + _CLOUD_CHUNK_POINTS)
                             for first in range(0, len(pixels), _CLOUD_CHUNK_POINTS)])
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
    consistency: float = defaults.CONSISTENCY,
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
        groups = sequence.phase_groups(axis)
        max_jump = _JUMP_OF_PERIOD * min(g.period for g in groups) if groups else np.inf
        decoded = decode(frames, sequence, min_quality=_MIN_QUALITY, edge_margin=0, saturation_level=full_scale,
                         max_jump=max_jump,
                         min_modulation=_MIN_MODULATION_OF_FULL_SCALE * full_scale, gray_boundaries=gray_boundaries,
                         max_indirect=max_indirect, consistency=consistency)
    coordinates = _refined_coordinates(decoded, sequence, axis, noise, gray_boundaries)
    coordinates = remove_speckles(coordinates, _coordinate_step_limit(sequence, axis))
    points_map = triangulate_map(table, coordinates)
    if report is not None:
        report = report.measured(np.isfinite(points_map).all(axis=-1))
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
    consistency: float = defaults.CONSISTENCY,
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
