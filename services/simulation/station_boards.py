"""Simulated station calibration: a ring of sensor heads and the board views that tie them together.

A station's heads look at the part from around it, so no board pose is seen by all of them; the heads are
tied by board poses that two neighbouring heads' cameras see at once, and each camera also films the board
alone (its own intrinsics). :func:`station_board_views` renders both for any rig with heads (a version-2 rig,
e.g. :func:`ring_station_rig`), with :func:`services.simulation.boards.render_board`.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np

from services.formats.board import ChessboardSpec
from services.formats.rig import Head, Rig
from services.geometry.camera_model import CameraModel
from services.simulation.boards import render_board

RING_HEADS = ("north", "east", "south", "west")
_CAMERA_SIZE, _CAMERA_FOCAL = (1280, 800), 1400.0
_PROJECTOR_SIZE, _PROJECTOR_FOCAL = (1280, 800), 1500.0


def _aimed(centre: np.ndarray, target: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """World-to-device rotation aiming z from ``centre`` at ``target``, x as near ``axis`` as it can be."""
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = axis - (axis @ forward) * forward
    right /= np.linalg.norm(right)
    return np.stack([right, np.cross(forward, right), forward])


def ring_station_rig(rng: np.random.Generator | None = None, *, heads: int = 4, radius_mm: float = 600.0,
                     baseline_mm: float = 250.0, scale: float = 1.0) -> Rig:
    """Sensor heads evenly around a horizontal part axis (world x), each a camera and a projector.

    Parameters
    ----------
    rng : numpy Generator, optional
        Draws a random station: each head turned by up to 5 degrees from its even place, at 0.92..1.08 of
        ``radius_mm``, its camera's focal length within 5 %, principal point within 2 % of the size, k1 in
        -0.15..0, k2 in 0..0.15. None gives the nominal station.
    heads : int
        Number of heads, named after :data:`RING_HEADS` (then ``head-4``, ...).
    radius_mm : float
        Distance of each head from the axis.
    baseline_mm : float
        Camera-projector distance of a head, along the axis; both aim at the axis.
    scale : float
        Shrinks the cameras' images and focal lengths alike (the same view at a lower resolution, for tests).

    Returns
    -------
    Rig
        Devices ``camera-NAME`` and ``projector-NAME`` of each head, the heads in order around the axis.
    """
    if heads < 2:
        raise ValueError(f"A station has at least two heads; got {heads}.")
    axis = np.array([1.0, 0.0, 0.0])
    devices, station_heads = {}, []
    width, height = round(_CAMERA_SIZE[0] * scale), round(_CAMERA_SIZE[1] * scale)
    for index in range(heads):
        name = RING_HEADS[index] if index < len(RING_HEADS) else f"head-{index}"
        angle = 2 * np.pi * index / heads
        radius, focal, shift, k = radius_mm, _CAMERA_FOCAL * scale, np.zeros(2), (-0.08, 0.12)
        if rng is not None:
            angle += np.radians(rng.uniform(-5, 5))
            radius *= rng.uniform(0.92, 1.08)
            focal *= rng.uniform(0.95, 1.05)
            shift = rng.uniform(-0.02, 0.02, 2) * (width, height)
            k = (rng.uniform(-0.15, 0.0), rng.uniform(0.0, 0.15))
        place = radius * np.array([0.0, np.sin(angle), -np.cos(angle)])
        target = np.zeros(3)
        for kind, offset in (("camera", baseline_mm / 2), ("projector", -baseline_mm / 2)):
            centre = place + offset * axis
            R = _aimed(centre, target, axis)
            if kind == "camera":
                K = [[focal, 0.0, (width - 1) / 2 + shift[0]], [0.0, focal, (height - 1) / 2 + shift[1]],
                     [0.0, 0.0, 1.0]]
                device = CameraModel(kind="camera", width=width, height=height, K=K, dist=[k[0], k[1], 0.0, 0.0, 0.0],
                                     R=R, t=-R @ centre)
            else:
                w, h = _PROJECTOR_SIZE
                K = [[_PROJECTOR_FOCAL, 0.0, (w - 1) / 2], [0.0, _PROJECTOR_FOCAL, (h - 1) / 2], [0.0, 0.0, 1.0]]
                device = CameraModel(kind="projector", width=w, height=h, K=K, dist=[], R=R, t=-R @ centre)
            devices[f"{kind}-{name}"] = device
        station_heads.append(Head(name, f"camera-{name}", f"projector-{name}"))
    return Rig(devices, station_heads=tuple(station_heads))


@dataclass(frozen=True)
class StationBoardViews:
    """Board views of a station's cameras.

    Attributes
    ----------
    board : ChessboardSpec
    poses : list of ((3, 3), (3,)) arrays
        Each view's true board-to-world pose, x_world = R x_board + t.
    images : dict of str to dict of int to (H, W) uint8 array
        Per camera (device name), the views it sees (view index -> image); a view two cameras see is a shared one.
    """

    board: ChessboardSpec
    poses: list[tuple[np.ndarray, np.ndarray]]
    images: dict[str, dict[int, np.ndarray]]


def station_board_poses(cameras: Sequence[CameraModel], board: ChessboardSpec, rng: np.random.Generator,
                        shared: int, own: int, pairs: Collection[tuple[int, int]] | None = None
                        ) -> tuple[list[tuple[np.ndarray, np.ndarray]], list[tuple[int, ...]]]:
    """Board poses (R, t: board to world) that pairs of cameras see together and that each camera sees alone, and
    for each pose the indices of the cameras that see it; ``shared`` poses per pair (only the ``pairs`` given, if
    any), ``own`` per camera (see :func:`station_board_views`, Notes)."""
    outline = _outline(board)
    poses, seen = [], []
    for a in range(len(cameras)):
        for b in range(a + 1, len(cameras)):
            if pairs is not None and (a, b) not in pairs:
                continue
            found = _shared_poses(cameras[a], cameras[b], board, outline, rng, shared)
            poses += found
            seen += [(a, b)] * len(found)
    for a, camera in enumerate(cameras):
        found = _own_poses(camera, board, outline, rng, own)
        poses += found
        seen += [(a,)] * len(found)
    return poses, seen


def station_board_views(rig: Rig, board: ChessboardSpec, rng: np.random.Generator, *, shared: int = 6,
                        own: int = 8, blur_sigma: float = 0.7, noise_sigma: float = 1.5,
                        supersample: int = 2) -> StationBoardViews:
    """Render the board in poses neighbouring heads' cameras see together, and in poses each camera sees alone.

    Parameters
    ----------
    rig : Rig
        A station (its heads' cameras are filmed).
    board : ChessboardSpec
    rng : numpy Generator
    shared : int
        Views per pair of cameras that can see the board together (neighbouring heads).
    own : int
        Views per camera alone, tilted 15..40 degrees, for its intrinsics.
    blur_sigma, noise_sigma, supersample
        As for :func:`services.simulation.boards.render_board`.

    Returns
    -------
    StationBoardViews

    Notes
    -----
    A shared pose faces the bisector of the two cameras' directions from the point nearest both optical axes,
    is shifted by up to 40 mm and tilted by up to 15 degrees; it is kept when every corner of the board and its
    one-square margin falls at least 10 px inside both images. A pair of cameras that no such pose fits (heads
    facing each other across the part) gets no shared view.
    """
    cameras = [rig.devices[head.camera] for head in rig.heads]
    names = [head.camera for head in rig.heads]
    if len(cameras) < 2:
        raise ValueError(f"A station's board views need at least two head cameras; the rig has {len(cameras)}.")
    poses, seen = station_board_poses(cameras, board, rng, shared, own)
    images: dict[str, dict[int, np.ndarray]] = {name: {} for name in names}
    for view, ((R, t), which) in enumerate(zip(poses, seen)):
        for camera in which:
            device = cameras[camera]
            images[names[camera]][view] = render_board(
                board, device.K, device.dist, device.R @ R, device.R @ t + device.t, device.size,
                blur_sigma=blur_sigma, noise_sigma=noise_sigma, supersample=supersample, rng=rng)
    return StationBoardViews(board, poses, images)


def _outline(board: ChessboardSpec) -> np.ndarray:
    points = board.object_points()
    square = board.square_mm
    low, high = points[:, :2].min(axis=0) - square, points[:, :2].max(axis=0) + square
    corners = np.array([[low[0], low[1], 0], [high[0], low[1], 0], [high[0], high[1], 0], [low[0], high[1], 0]])
    return np.concatenate([points, corners])


def _board_pose(centre: np.ndarray, normal: np.ndarray, board: ChessboardSpec, rng: np.random.Generator,
                tilt_deg: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """Board-to-world pose: the board's middle at ``centre``, its back (board z) along -``normal`` turned by a
    tilt drawn from ``tilt_deg`` about a random in-plane axis, and spun by up to 10 degrees."""
    z = -normal / np.linalg.norm(normal)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    if np.linalg.norm(x) < 0.1:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    frame = np.column_stack([x, np.cross(z, x), z])
    spin = np.radians(rng.uniform(-10, 10))
    direction = rng.uniform(0, 2 * np.pi)
    tilt = np.radians(rng.uniform(*tilt_deg))
    R = frame @ _rotation(np.array([0.0, 0.0, spin])) @ _rotation(tilt * np.array([np.cos(direction),
                                                                                  np.sin(direction), 0.0]))
    middle = board.object_points().mean(axis=0)
    return R, centre - R @ middle


def _rotation(rvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rvec)
    if angle == 0:
        return np.eye(3)
    k = rvec / angle
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross


def _inside(camera: CameraModel, R: np.ndarray, t: np.ndarray, outline: np.ndarray, margin: float = 10.0) -> bool:
    world = outline @ R.T + t
    in_camera = world @ camera.R.T + camera.t
    if np.any(in_camera[:, 2] <= 0):
        return False
    facing = (camera.R @ R[:, 2]) @ np.array([0.0, 0.0, 1.0])  # the board's back faces away from the camera
    if facing < np.cos(np.radians(65)):
        return False
    pixels = camera.project(world)
    return bool(np.all(pixels >= margin) and np.all(pixels <= np.array(camera.size) - 1 - margin))


def _nearest_point(a: CameraModel, b: CameraModel) -> np.ndarray:
    """The point midway between the two optical axes where they come nearest."""
    centres = [a.centre, b.centre]
    directions = [a.R[2], b.R[2]]
    w = centres[0] - centres[1]
    d1, d2 = directions
    denominator = 1 - (d1 @ d2) ** 2
    if denominator < 1e-9:
        return (centres[0] + centres[1]) / 2 + 600 * d1
    s = ((d1 @ d2) * (d2 @ w) - d1 @ w) / denominator
    u = (d2 @ w - (d1 @ d2) * (d1 @ w)) / denominator
    return (centres[0] + s * d1 + centres[1] + u * d2) / 2


def _shared_poses(a: CameraModel, b: CameraModel, board, outline, rng, count, attempts: int = 3000):
    middle = _nearest_point(a, b)
    towards = [(c.centre - middle) / np.linalg.norm(c.centre - middle) for c in (a, b)]
    if towards[0] @ towards[1] < np.cos(np.radians(120)):
        return []
    normal = towards[0] + towards[1]
    poses = []
    for _ in range(attempts):
        if len(poses) == count:
            break
        R, t = _board_pose(middle + rng.uniform(-40, 40, 3), normal, board, rng, (0.0, 15.0))
        if _inside(a, R, t, outline) and _inside(b, R, t, outline):
            poses.append((R, t))
    return poses


def _own_poses(camera: CameraModel, board, outline, rng, count, attempts: int = 3000):
    poses = []
    for _ in range(attempts):
        if len(poses) == count:
            break
        depth = rng.uniform(0.8, 1.15) * np.linalg.norm(camera.centre)
        reach = 0.25 * depth * np.array(camera.size) / camera.K[0, 0]
        in_camera = np.array([rng.uniform(-1, 1) * reach[0], rng.uniform(-1, 1) * reach[1], depth])
        centre = camera.R.T @ (in_camera - camera.t)
        R, t = _board_pose(centre, camera.centre - centre, board, rng, (15.0, 40.0))
        if _inside(camera, R, t, outline):
            poses.append((R, t))
    if len(poses) < count:
        raise ValueError(f"Only {len(poses)} of {count} board poses fit the camera's image; the board is too large.")
    return poses
