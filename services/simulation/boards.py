"""Render what a camera sees of a calibration board: visible, or hollowed before a heater (infrared).

Every camera sample is traced to the board plane (ray/plane intersection through the lens
model) and looks up a board texture with ``cv2.remap``; samples are averaged over each pixel
(supersampling), then optical blur, sensor noise and quantisation are applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

from services.formats.board import BoardSpec, CharucoSpec, ChessboardSpec, CirclesSpec
from services.geometry.camera import normalized_coordinates, project_points
from services.geometry.camera_model import CameraModel

Modality = Literal["visible", "infrared"]
_MAX_TEXELS_PER_FEATURE = 256
_BACKGROUND = 0.35  # visible albedo of the scene behind the board
_PRINTED_BLACK, _PAPER_WHITE = 0.08, 0.95  # visible chessboard albedos


def render_board(
    board: BoardSpec,
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    image_size: tuple[int, int],
    *,
    modality: Modality = "visible",
    blur_sigma: float = 0.0,
    noise_sigma: float = 0.0,
    supersample: int = 3,
    bit_depth: int = 8,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Render one grey camera frame of a calibration board.

    Parameters
    ----------
    board : BoardSpec
        The board; features sit at ``board.object_points()`` in board millimetres.
    K, dist : arrays
        Camera intrinsics and OpenCV distortion coefficients.
    R, t : (3, 3) and (3,) arrays
        Board-to-camera pose, x_cam = R x_board + t.
    image_size : (width, height)
    modality : {"visible", "infrared"}
        "visible": dark squares, markers or dots on a white board with a white margin of one
        square. "infrared": a hollowed chessboard (its light squares cut out) before a heater,
        as in the paper's section 2.2: the holes glow with the heater's radiance, which falls
        off from the board centre, while the solid squares and the frame stay cool, so the
        board looks inverted and has no light border.
    blur_sigma : float
        Standard deviation of the Gaussian optical blur, in pixels.
    noise_sigma : float
        Standard deviation of additive Gaussian sensor noise, in grey levels of the output.
    supersample : int
        Samples per pixel along each axis.
    bit_depth : {8, 16}
        Output type uint8 or uint16.
    rng : numpy Generator, optional
        Source of the noise (a fixed seed when omitted).

    Returns
    -------
    image : (height, width) uint8 or uint16 array

    Notes
    -----
    A sample at pixel p has the viewing ray (x, y, 1) with (x, y) = undistort(p); it meets the
    board plane z = 0 at the board point (X, Y) with [r1 r2 t] (X, Y, 1)^T ~ (x, y, 1)^T, r1
    and r2 the first columns of R (the plane-to-image homography of Zhang's method). The
    texture has an integer number of texels per square, so square edges fall on texel
    boundaries and bilinear lookup puts them exactly in place.
    """
    if modality not in ("visible", "infrared"):
        raise ValueError(f"modality must be 'visible' or 'infrared'; got {modality!r}.")
    if modality == "infrared" and not isinstance(board, ChessboardSpec):
        raise ValueError("Only a chessboard can be hollowed for infrared rendering; got a " + board.type + " board.")
    if bit_depth not in (8, 16):
        raise ValueError(f"bit_depth must be 8 or 16; got {bit_depth}.")
    if supersample < 1:
        raise ValueError(f"supersample must be at least 1; got {supersample}.")
    width, height = int(image_size[0]), int(image_size[1])
    samples, _, _ = _board_samples(board, K, dist, R, t, width, height, supersample, modality)
    radiance = cv2.resize(samples, (width, height), interpolation=cv2.INTER_AREA)  # the mean of each pixel's samples
    if blur_sigma > 0:
        radiance = cv2.GaussianBlur(radiance, (0, 0), blur_sigma)
    return _quantise(radiance, noise_sigma, bit_depth, rng or np.random.default_rng(0))


def render_board_capture(
    board: BoardSpec,
    K: np.ndarray,
    dist: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    image_size: tuple[int, int],
    projector: CameraModel,
    patterns: np.ndarray,
    *,
    ambient: float = 0.05,
    blur_sigma: float = 0.0,
    noise_sigma: float = 0.0,
    supersample: int = 2,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Camera frames of a board lit by a projector showing each pattern (projector calibration captures).

    Parameters
    ----------
    board, K, dist, R, t, image_size
        As for ``render_board``; (R, t) is the board-to-camera pose.
    projector : CameraModel
        The projector, its pose mapping camera coordinates to projector coordinates.
    patterns : (F, Hp, Wp) uint8 array
        The projector images.
    ambient : float
        Ambient light as a fraction of full projector light.
    blur_sigma, noise_sigma, supersample, rng
        As for ``render_board`` (8-bit output).

    Returns
    -------
    frames : (F, height, width) uint8 array

    Notes
    -----
    Each sample's board point X (see ``render_board``) has albedo rho(X) (the visible board
    texture) and projector pixel x_p = proj(K_p, dist_p, R_p, t_p, X); its irradiance is
    E = rho(X) (ambient + L(x_p)) with L the pattern value sampled bilinearly (0 outside the
    projector image). The board plane casts no shadow on itself.
    """
    patterns = np.asarray(patterns)
    if patterns.ndim != 3 or patterns.shape[1:] != (projector.height, projector.width):
        raise ValueError(f"patterns must have shape (F, {projector.height}, {projector.width}); got {patterns.shape}.")
    width, height = int(image_size[0]), int(image_size[1])
    albedo, board_xy, valid = _board_samples(board, K, dist, R, t, width, height, supersample, "visible")
    points = np.column_stack([board_xy.reshape(-1, 2), np.zeros(board_xy[..., 0].size)])
    points = points @ np.asarray(R, np.float64).T + np.asarray(t, np.float64).ravel()
    projector_pixels = np.full((len(points), 2), -1e6)
    chosen = valid.ravel()
    projector_pixels[chosen] = project_points(points[chosen], projector.K, projector.dist,
                                              projector.R, projector.t)
    projector_pixels = np.nan_to_num(projector_pixels, nan=-1e6).astype(np.float32)
    map_x = projector_pixels[:, 0].reshape(albedo.shape)
    map_y = projector_pixels[:, 1].reshape(albedo.shape)
    maximum = float(np.iinfo(patterns.dtype).max) if np.issubdtype(patterns.dtype, np.integer) else 1.0
    rng = rng or np.random.default_rng(0)
    frames = np.empty((len(patterns), height, width), np.uint8)
    for index, pattern in enumerate(patterns):
        light = cv2.remap(pattern.astype(np.float32) / maximum, map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        irradiance = cv2.resize(albedo * (ambient + light), (width, height), interpolation=cv2.INTER_AREA)
        if blur_sigma > 0:
            irradiance = cv2.GaussianBlur(irradiance, (0, 0), blur_sigma)
        frames[index] = _quantise(irradiance, noise_sigma, 8, rng)
    return frames


def _board_samples(board, K, dist, R, t, width, height, supersample, modality):
    """Radiance (albedo when visible) of every sample, its board coordinates and whether it sees the board plane."""
    board_xy, valid = _sample_board_coordinates(K, dist, R, t, width, height, supersample)
    texels_per_mm = _texture_resolution(board, board_xy[valid])
    texture, origin = _board_texture(board, modality, texels_per_mm)
    map_x = ((board_xy[..., 0] - origin[0]) * texels_per_mm - 0.5).astype(np.float32)
    map_y = ((board_xy[..., 1] - origin[1]) * texels_per_mm - 0.5).astype(np.float32)
    map_x[~valid] = -1e6
    background = 0.0 if modality == "infrared" else _BACKGROUND
    samples = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                        borderValue=background)
    if modality == "infrared":
        samples = _apply_heater(samples, board_xy, valid, board)
    return samples, board_xy, valid


def _sample_board_coordinates(K, dist, R, t, width, height, supersample):
    """Board (x, y) in mm seen by every sample, and whether the sample's ray meets the board's front."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    u = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    v = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    x, y = _undistorted_field(K, dist, u, v)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).ravel()
    # The ray (x, y, 1) meets the plane z_board = 0 where [r1 r2 t] (X, Y, 1)^T ~ (x, y, 1)^T.
    to_board = np.linalg.inv(np.column_stack([R[:, 0], R[:, 1], t]))
    homogeneous = [to_board[row, 0] * x + to_board[row, 1] * y + to_board[row, 2] for row in range(3)]
    with np.errstate(divide="ignore", invalid="ignore"):
        board_xy = np.stack([homogeneous[0] / homogeneous[2], homogeneous[1] / homogeneous[2]], axis=-1)
    valid = np.isfinite(board_xy).all(axis=-1) & (homogeneous[2] > 0)  # in front of the camera
    return np.where(valid[..., None], board_xy, 0.0), valid


def _undistorted_field(K, dist, u, v, step: int = 4):
    """Normalised coordinates (x, y), each (len(v), len(u)), of the samples at columns u and rows v.

    The iterative lens inversion runs on a lattice of one point every ``step`` pixels and the
    samples interpolate it with Keys' cubic kernel: the field is smooth, so the error stays far
    below a micro-pixel, and it is many times faster than inverting every sample. Samples form a
    tensor grid, so the interpolation is two small matrix products W_v F W_u^T.
    """
    lattice_u = np.arange(np.floor(u[0]) - 2 * step, np.ceil(u[-1]) + 3 * step, step)
    lattice_v = np.arange(np.floor(v[0]) - 2 * step, np.ceil(v[-1]) + 3 * step, step)
    grid_u, grid_v = np.meshgrid(lattice_u, lattice_v)
    field = normalized_coordinates(np.column_stack([grid_u.ravel(), grid_v.ravel()]), K, dist)
    field = field.reshape(len(lattice_v), len(lattice_u), 2)
    weights_u = _cubic_weights((u - lattice_u[0]) / step, len(lattice_u))
    weights_v = _cubic_weights((v - lattice_v[0]) / step, len(lattice_v))
    return tuple(weights_v @ field[..., axis] @ weights_u.T for axis in range(2))


def _cubic_weights(positions: np.ndarray, size: int) -> np.ndarray:
    """(len(positions), size) matrix interpolating samples at integer nodes with Keys' kernel (a = -0.5)."""
    distance = np.abs(positions[:, None] - np.arange(size)[None, :])
    near = (1.5 * distance - 2.5) * distance**2 + 1
    far = ((-0.5 * distance + 2.5) * distance - 4) * distance + 2
    return np.where(distance < 1, near, np.where(distance < 2, far, 0.0))


def _feature_pitch(board: BoardSpec) -> float:
    return board.spacing_mm if isinstance(board, CirclesSpec) else board.square_mm


def _texture_resolution(board: BoardSpec, board_xy: np.ndarray) -> float:
    """Texels per mm: about one texel per camera sample, an integer number per square."""
    pitch = _feature_pitch(board)
    if len(board_xy) < 2:
        return 8.0 / pitch
    span = np.ptp(board_xy, axis=0).max()
    samples_across = np.sqrt(len(board_xy))
    texels_per_square = int(np.clip(np.ceil(pitch * samples_across / max(span, 1e-9)), 8, _MAX_TEXELS_PER_FEATURE))
    return texels_per_square / pitch


def _board_texture(board: BoardSpec, modality: Modality, texels_per_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Float32 texture in [0, 1] and the board coordinates (mm) of its top-left texel corner."""
    pitch = _feature_pitch(board)
    n = int(round(pitch * texels_per_mm))
    if isinstance(board, ChessboardSpec):
        cols, rows = board.pattern_size
        squares = np.indices((rows + 1, cols + 1)).sum(axis=0) % 2
        light = np.kron(squares, np.ones((n, n))).astype(np.float32)  # square (0, 0) dark
        if modality == "infrared":  # 1 marks a hole; the frame is solid
            return np.pad(light, n, constant_values=0.0), np.array([-2 * pitch, -2 * pitch])
        albedo = _PRINTED_BLACK + (_PAPER_WHITE - _PRINTED_BLACK) * light
        return np.pad(albedo, n, constant_values=_PAPER_WHITE), np.array([-2 * pitch, -2 * pitch])
    if isinstance(board, CharucoSpec):
        cols, rows = board.squares
        image = board.opencv_board().generateImage((cols * n, rows * n), marginSize=0, borderBits=1)
        texture = np.pad(image.astype(np.float32) / 255.0, n, constant_values=1.0)
        return texture, np.array([-2 * pitch, -2 * pitch])
    object_points = board.object_points()
    low = object_points[:, :2].min(axis=0) - pitch
    extent = object_points[:, :2].max(axis=0) + pitch - low
    texture = np.ones((int(np.ceil(extent[1] * texels_per_mm)), int(np.ceil(extent[0] * texels_per_mm))), np.float32)
    shift = 8
    for x, y in object_points[:, :2]:
        centre = (int(round(((x - low[0]) * texels_per_mm - 0.5) * 2**shift)),
                  int(round(((y - low[1]) * texels_per_mm - 0.5) * 2**shift)))
        cv2.circle(texture, centre, int(round(0.25 * pitch * texels_per_mm * 2**shift)), 0.0, -1, cv2.LINE_AA, shift)
    return texture, low


def _apply_heater(holes: np.ndarray, board_xy: np.ndarray, valid: np.ndarray, board: ChessboardSpec) -> np.ndarray:
    """Radiance of a hollowed board: heater glow through the holes, cool solid parts."""
    cols, rows = board.pattern_size
    centre = np.array([(cols - 1) / 2, (rows - 1) / 2]) * board.square_mm
    radius = 1.5 * np.hypot(cols + 1, rows + 1) * board.square_mm
    falloff = np.exp(-np.sum((board_xy - centre) ** 2, axis=-1) / radius**2)
    cool_board, heater = 0.12, 0.95
    radiance = np.where(valid, cool_board + (heater * falloff - cool_board) * holes, 0.05)
    return radiance.astype(np.float32)


def _quantise(radiance: np.ndarray, noise_sigma: float, bit_depth: int, rng: np.random.Generator) -> np.ndarray:
    full_scale = 255.0 if bit_depth == 8 else 65535.0
    grey = radiance * (0.9 * full_scale) + 0.04 * full_scale
    if noise_sigma > 0:
        grey = grey + rng.normal(0.0, noise_sigma, grey.shape)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    return np.clip(np.round(grey), 0, full_scale).astype(dtype)


@dataclass(frozen=True)
class SimulatedCalibration:
    """A simulated calibration session: a camera drawn at random, its board and the rendered views.

    Attributes
    ----------
    modality : {"visible", "infrared"}
    image_size : (width, height)
    K, dist : arrays
        The true intrinsics and OpenCV distortion (k1, k2, p1, p2, k3).
    board : ChessboardSpec
    poses : list of ((3, 3), (3,)) arrays
        The true board-to-camera pose of every view.
    images : list of (H, W) uint8 arrays
    blur_sigma, noise_sigma : float
        Optical blur (px) and sensor noise (grey levels) of the views.
    """

    modality: Modality
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    board: ChessboardSpec
    poses: list[tuple[np.ndarray, np.ndarray]]
    images: list[np.ndarray]
    blur_sigma: float
    noise_sigma: float


THERMAL_SIZES = ((160, 120), (320, 240), (320, 256), (384, 288), (640, 512))
VISIBLE_SIZES = ((640, 480), (752, 480), (800, 600), (1024, 768))


def random_calibration(
    rng: np.random.Generator,
    *,
    modality: Modality | None = None,
    image_size: tuple[int, int] | None = None,
    views: int | None = None,
    blur_sigma: float | None = None,
    noise_sigma: float | None = None,
    tilt_axis: np.ndarray | None = None,
) -> SimulatedCalibration:
    """Draw a camera, a chessboard and a set of board views at random, and render them.

    Parameters
    ----------
    rng : numpy Generator
    modality : {"visible", "infrared"}, optional
        Infrared renders the hollowed heated board; drawn with equal odds when omitted.
    image_size : (width, height), optional
        Drawn from ``THERMAL_SIZES`` or ``VISIBLE_SIZES`` when omitted.
    views : int, optional
        Number of views, drawn from 8..20 when omitted.
    blur_sigma, noise_sigma : float, optional
        Drawn from 0.4..1.5 px and 0.5..3 grey levels when omitted.
    tilt_axis : (2,) array, optional
        Tilt every view about this one axis of the board (x, y) instead of axes drawn all around: a
        degenerate set that leaves the principal point undetermined along the other axis.

    Returns
    -------
    SimulatedCalibration

    Notes
    -----
    The camera: a horizontal field of view of 25..65 degrees (f = w / (2 tan(fov / 2))), square pixels
    within 0.3 %, the principal point within 3 % of the size from the centre, k1 in -0.35..0.05,
    k2 in -0.05..0.2 (half the time zero), p1 and p2 within 0.001, k3 zero. The board: a chessboard of
    5..10 by 4..7 inner corners (fewer rows than columns) whose width covers 35..70 % of the image at the middle depth, placed at
    depths spread over a factor 1.6, tilted 10..45 degrees, every corner at least a square inside the
    image. Views the caller's detector misses are the caller's to count.
    """
    modality = modality or ("infrared" if rng.uniform() < 0.5 else "visible")
    if modality not in ("visible", "infrared"):
        raise ValueError(f"modality must be 'visible' or 'infrared'; got {modality!r}.")
    sizes = THERMAL_SIZES if modality == "infrared" else VISIBLE_SIZES
    width, height = image_size or sizes[rng.integers(len(sizes))]
    views = int(views if views is not None else rng.integers(8, 21))
    if views < 1:
        raise ValueError(f"views must be at least 1; got {views}.")
    blur_sigma = float(blur_sigma if blur_sigma is not None else rng.uniform(0.4, 1.5))
    noise_sigma = float(noise_sigma if noise_sigma is not None else rng.uniform(0.5, 3.0))
    fov = np.radians(rng.uniform(25.0, 65.0))
    fx = width / (2 * np.tan(fov / 2))
    fy = fx * (1 + rng.uniform(-0.003, 0.003))
    K = np.array([[fx, 0.0, (width - 1) / 2 + rng.uniform(-0.03, 0.03) * width],
                  [0.0, fy, (height - 1) / 2 + rng.uniform(-0.03, 0.03) * height], [0.0, 0.0, 1.0]])
    dist = np.array([rng.uniform(-0.35, 0.05), rng.uniform(-0.05, 0.2) * (rng.uniform() < 0.5),
                     rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), 0.0])
    for _ in range(10):  # a board no pose fits (too large for a strongly distorted lens) is drawn again
        cols = int(rng.integers(5, 11))
        rows = int(rng.integers(4, min(8, cols)))  # fewer rows than columns: the board's orientation is unambiguous
        square = float(rng.choice([15.0, 20.0, 25.0, 30.0, 40.0]))
        board = ChessboardSpec(type="chessboard", inner_corners=(cols, rows), square_mm=square)
        cover = rng.uniform(0.35, 0.7)
        middle = fx * (cols + 1) * square / (cover * width)
        try:
            poses = _random_poses(rng, board, K, dist, (width, height), views, (middle / 1.25, middle * 1.25),
                                  tilt_axis)
            break
        except ValueError:
            continue
    else:
        raise ValueError("No board of those drawn fits this camera's image.")
    images = [render_board(board, K, dist, R, t, (width, height), modality=modality, blur_sigma=blur_sigma,
                           noise_sigma=noise_sigma, supersample=2, rng=rng) for R, t in poses]
    return SimulatedCalibration(modality, (int(width), int(height)), K, dist, board, poses, images, blur_sigma,
                                noise_sigma)


def _random_poses(rng, board, K, dist, size, views, depths, tilt_axis):
    """Tilted board poses at spread depths with every corner at least a square inside the image."""
    points = board.object_points()
    centre = points.mean(axis=0)
    square = board.square_mm
    frame = np.array([[points[:, 0].min() - square, points[:, 1].min() - square, 0.0],
                      [points[:, 0].max() + square, points[:, 1].min() - square, 0.0],
                      [points[:, 0].max() + square, points[:, 1].max() + square, 0.0],
                      [points[:, 0].min() - square, points[:, 1].max() + square, 0.0]])
    outline = np.concatenate([points, frame])
    poses, attempts = [], 0
    while len(poses) < views:
        attempts += 1
        if attempts > 200 * views:
            raise ValueError("No board pose fits the image; the board is too large for this camera.")
        index = len(poses)
        if tilt_axis is None:
            angle = 2 * np.pi * (index + rng.uniform()) / views
            axis = np.array([np.cos(angle), np.sin(angle)])
        else:
            axis = np.asarray(tilt_axis, float) / np.linalg.norm(tilt_axis) * rng.choice([-1.0, 1.0])
        tilt = np.radians(rng.uniform(10, 45))
        R = cv2.Rodrigues(np.array([tilt * axis[0], tilt * axis[1], rng.uniform(-0.3, 0.3)]))[0]
        z = depths[0] + (depths[1] - depths[0]) * (index + rng.uniform()) / views
        reach = 0.3 * z * np.array(size) / K[0, 0]
        t = np.array([rng.uniform(-1, 1) * reach[0], rng.uniform(-1, 1) * reach[1], z]) - R @ centre
        projected = cv2.projectPoints(outline, cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
        if projected.min() >= 2 and np.all(projected.max(axis=0) <= np.array(size) - 3):
            poses.append((R, t))
    return poses
