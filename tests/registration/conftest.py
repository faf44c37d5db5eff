"""Visible/infrared pairs with known infrared-to-visible matrices, shared by the registration tests."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import pytest

from services.registration.synthetic_pairs import infrared_from_visible, random_transform, render_scene_pair

CHESSBOARD_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "opencv-chessboard"  # shared/ beside the clone
INFRARED_SIZE = (320, 256)


@lru_cache(maxsize=None)
def chessboard_pair(seed: int, index: int, **transform_ranges: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A real visible photograph, an infrared-like view of it and the true matrix (cached: do not modify)."""
    visible = cv2.imread(str(CHESSBOARD_DIR / f"left{index:02d}.jpg"), cv2.IMREAD_GRAYSCALE)
    if visible is None:
        pytest.fail(f"the shared chessboard image left{index:02d}.jpg is missing from {CHESSBOARD_DIR}")
    rng = np.random.default_rng(seed)
    matrix = random_transform(rng, INFRARED_SIZE, (visible.shape[1], visible.shape[0]), 1.8, **transform_ranges)
    return visible, infrared_from_visible(rng, visible, matrix, INFRARED_SIZE), matrix


@lru_cache(maxsize=None)
def scene_pair(seed: int, **transform_ranges: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A rendered 1024x768 visible and 320x256 infrared view of one scene and the true matrix (cached)."""
    rng = np.random.default_rng(seed)
    matrix = random_transform(rng, INFRARED_SIZE, (1024, 768), 3.0, **transform_ranges)
    visible, infrared = render_scene_pair(rng, matrix)
    return visible, infrared, matrix
