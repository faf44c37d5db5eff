"""Simulated cameras and board poses: an infrared camera, a visible camera beside it, and board views."""

from __future__ import annotations

import cv2
import numpy as np

from services.geometry.camera_model import CameraModel
from services.simulation.boards import render_board, render_board_capture
from services.structured_light.patterns import generate_sequence

THERMAL_SIZE = (320, 256)
THERMAL_K = np.array([[400.0, 0.0, 161.3], [0.0, 400.0, 127.6], [0.0, 0.0, 1.0]])
THERMAL_DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])


def board_poses(board, count: int, distance: float, tilt_deg: float, spread_mm: float = 25.0):
    """Board-to-camera poses circling the optical axis: tilted by ``tilt_deg`` in turning directions."""
    centre = board.object_points().mean(axis=0)
    poses = []
    for index in range(count):
        angle = 2 * np.pi * index / count
        tilt = np.deg2rad(tilt_deg)
        rotation_vector = np.array([tilt * np.cos(angle), tilt * np.sin(angle), np.deg2rad(10 * np.sin(3 * angle))])
        R = cv2.Rodrigues(rotation_vector)[0]
        offset = np.array([spread_mm * np.cos(2 * angle), 0.8 * spread_mm * np.sin(2 * angle),
                           distance * (1 + 0.1 * np.cos(3 * angle))])
        poses.append((R, offset - R @ centre))
    return poses


def project(board, K, dist, R, t) -> np.ndarray:
    return cv2.projectPoints(board.object_points(), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)


CAMERA_SIZE = (640, 480)
CAMERA_K = np.array([[700.0, 0.0, 322.0], [0.0, 700.0, 241.0], [0.0, 0.0, 1.0]])
CAMERA_DIST = np.array([-0.1, 0.05, 0.0, 0.0, 0.0])
THERMAL_FROM_CAMERA = (cv2.Rodrigues(np.array([0.01, -0.06, 0.02]))[0], np.array([-60.0, 2.0, 1.5]))


def render_pairs(board, count: int, seed: int = 11) -> list[tuple[np.ndarray, np.ndarray]]:
    """(visible, infrared) frames of ``count`` board poses seen by both cameras."""
    rng = np.random.default_rng(seed)
    R_rel, t_rel = THERMAL_FROM_CAMERA
    pairs = []
    for R, t in board_poses(board, count, 480.0, 25.0, spread_mm=15.0):
        visible = render_board(board, CAMERA_K, CAMERA_DIST, R, t + np.array([30.0, 0, 0]), CAMERA_SIZE,
                               blur_sigma=0.7, noise_sigma=1.5, supersample=2, rng=rng)
        infrared = render_board(board, THERMAL_K, THERMAL_DIST, R_rel @ R, R_rel @ (t + np.array([30.0, 0, 0])) + t_rel,
                                THERMAL_SIZE, modality="infrared", blur_sigma=1.0, noise_sigma=2.0, supersample=2,
                                rng=rng)
        pairs.append((visible, infrared))
    return pairs


PROJECTOR_CAMERA_SIZE = (480, 360)
PROJECTOR_CAMERA_K = np.array([[560.0, 0.0, 240.5], [0.0, 560.0, 179.0], [0.0, 0.0, 1.0]])
PROJECTOR_CAMERA_DIST = np.array([-0.05, 0.02, 0.0, 0.0, 0.0])


def projector_beside_camera() -> CameraModel:
    """A 400x300 projector 150 mm left of the camera, turned 15 degrees toward its axis (pose from the camera)."""
    R = cv2.Rodrigues(np.array([0.0, np.radians(-15.0), 0.0]))[0]
    centre = np.array([-150.0, 5.0, 10.0])
    return CameraModel(kind="projector", width=400, height=300,
                  K=[[600.0, 0.0, 199.5], [0.0, 600.0, 170.0], [0.0, 0.0, 1.0]], dist=[0.03, -0.02, 0.0, 0.0],
                  R=R.tolist(), t=(-R @ centre).tolist())


def render_projector_captures(board, count: int, seed: int = 4):
    """(sequence, frames) of ``count`` board poses lit by ``projector_beside_camera`` with both axes coded."""
    projector = projector_beside_camera()
    sequence, patterns = generate_sequence(projector.width, projector.height, axes="xy", period=16, steps=4)
    rng = np.random.default_rng(seed)
    captures = []
    for R, t in board_poses(board, count, 520.0, 25.0, spread_mm=10.0):
        frames = render_board_capture(board, PROJECTOR_CAMERA_K, PROJECTOR_CAMERA_DIST, R, t, PROJECTOR_CAMERA_SIZE,
                                      projector, patterns, blur_sigma=0.7, noise_sigma=1.5, rng=rng)
        captures.append((sequence, frames, (R, t)))
    return captures
