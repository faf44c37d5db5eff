import cv2
import numpy as np
import pytest

from services.calibration.corners import detect_board, refine_corners
from services.formats.board import parse_board
from services.formats.images import read_frame
from services.simulation.boards import render_board

from .simulated_rig import THERMAL_DIST, THERMAL_K, THERMAL_SIZE, project

VISIBLE_K = np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]])
VISIBLE_DIST = np.array([-0.1, 0.05, 0.0, 0.0, 0.0])


def _pose(board, distance, rotation=(0.3, -0.2, 0.1)):
    R = cv2.Rodrigues(np.array(rotation))[0]
    return R, np.array([0.0, 0.0, distance]) - R @ board.object_points().mean(axis=0)


def _errors(detection, board, K, dist, R, t):
    truth = project(board, K, dist, R, t)[detection.ids]
    return np.linalg.norm(detection.image_points - truth, axis=1)


def test_visible_chessboard_corners_are_sub_pixel_accurate(chessboard_9x6):
    R, t = _pose(chessboard_9x6, 450)
    image = render_board(chessboard_9x6, VISIBLE_K, VISIBLE_DIST, R, t, (640, 480), blur_sigma=0.8, noise_sigma=1.5)
    detection = detect_board(image, chessboard_9x6)
    assert detection.polarity == "normal"
    errors = _errors(detection, chessboard_9x6, VISIBLE_K, VISIBLE_DIST, R, t)
    assert np.sqrt(np.mean(errors**2)) < 0.05
    assert errors.max() < 0.15


def test_hollow_infrared_board_is_found_in_the_visible_order(chessboard_9x6):
    R, t = _pose(chessboard_9x6, 380, rotation=(-0.35, 0.3, 3.0))  # upside down: order must still hold
    image = render_board(chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE, modality="infrared",
                         blur_sigma=1.0, noise_sigma=2.0)
    detection = detect_board(image, chessboard_9x6)
    errors = _errors(detection, chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t)
    assert errors.max() < 0.3


def test_sixteen_bit_infrared_frames_are_accepted(chessboard_9x6):
    R, t = _pose(chessboard_9x6, 380)
    image = render_board(chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE, modality="infrared",
                         blur_sigma=1.0, noise_sigma=200.0, bit_depth=16)
    assert image.dtype == np.uint16
    detection = detect_board(image, chessboard_9x6)
    assert _errors(detection, chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t).max() < 0.3


def test_fixed_polarity_is_respected(chessboard_9x6):
    R, t = _pose(chessboard_9x6, 380)
    image = render_board(chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t, THERMAL_SIZE, modality="infrared")
    inverted = chessboard_9x6.model_copy(update={"polarity": "inverted"})
    assert detect_board(image, inverted).polarity == "inverted"
    normal_only = chessboard_9x6.model_copy(update={"polarity": "normal"})
    detection = detect_board(image, normal_only)
    if detection is not None:  # if found with the wrong polarity, it must still be right
        assert _errors(detection, chessboard_9x6, THERMAL_K, THERMAL_DIST, R, t).max() < 0.5


def test_a_board_with_more_corners_than_the_spec_is_not_taken(opencv_left_images):
    smaller = parse_board('{"type": "chessboard", "inner_corners": [8, 6], "square_mm": 1.0}')
    found = [detect_board(read_frame(path), smaller) for path in opencv_left_images[:3]]
    assert found == [None, None, None]


def test_no_board_gives_none(chessboard_9x6):
    rng = np.random.default_rng(3)
    assert detect_board(rng.integers(0, 255, (240, 320), dtype=np.uint8), chessboard_9x6) is None


@pytest.mark.parametrize(
    "spec",
    [
        '{"type": "charuco", "squares": [7, 5], "square_mm": 30, "marker_mm": 22}',
        '{"type": "circles", "grid": [4, 11], "spacing_mm": 15, "asymmetric": true}',
        '{"type": "circles", "grid": [7, 5], "spacing_mm": 25}',
    ],
)
def test_charuco_and_circle_boards_are_detected(spec):
    board = parse_board(spec)
    R, t = _pose(board, 500)
    image = render_board(board, VISIBLE_K, VISIBLE_DIST, R, t, (640, 480), blur_sigma=0.8, noise_sigma=1.5)
    detection = detect_board(image, board)
    assert len(detection.ids) == len(board.object_points())
    assert _errors(detection, board, VISIBLE_K, VISIBLE_DIST, R, t).max() < 0.3


def test_refine_corners_needs_two_corners():
    with pytest.raises(ValueError, match="At least two corners"):
        refine_corners(np.zeros((10, 10), np.uint8), np.zeros((1, 2)))


def test_detect_board_refuses_colour_images(chessboard_9x6):
    with pytest.raises(ValueError, match="2-D uint8 or uint16"):
        detect_board(np.zeros((10, 10, 3), np.uint8), chessboard_9x6)
