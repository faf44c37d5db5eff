"""Shared fixtures: boards, the real OpenCV chessboard images, simulated visible/infrared pairs."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.formats.board import parse_board

from .simulated_rig import render_pairs, render_projector_captures

OPENCV_IMAGES = Path(__file__).parents[2].parent / "shared" / "data" / "opencv-chessboard"


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


@pytest.fixture(scope="session")
def visible_infrared_pairs(chessboard_9x6):
    return render_pairs(chessboard_9x6, 8)


@pytest.fixture(scope="session")
def chessboard_15mm():
    return parse_board('{"type": "chessboard", "inner_corners": [9, 6], "square_mm": 15.0}')


@pytest.fixture(scope="session")
def projector_captures(chessboard_15mm):
    return render_projector_captures(chessboard_15mm, 5)
