"""Shared simulated cameras, board poses and the real OpenCV chessboard images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from services.formats.board import parse_board

OPENCV_IMAGES = Path(__file__).parents[2].parent / "shared" / "data" / "opencv-chessboard"

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


@pytest.fixture(scope="session")
def chessboard_9x6():
    return parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 20.0}')


@pytest.fixture(scope="session")
def opencv_board():
    return parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 1.0}')


@pytest.fixture(scope="session")
def opencv_left_images() -> list[Path]:
    images = sorted(OPENCV_IMAGES.glob("left*.jpg"))
    assert len(images) == 13, f"expected OpenCV's 13 left chessboard images in {OPENCV_IMAGES}"
    return images
