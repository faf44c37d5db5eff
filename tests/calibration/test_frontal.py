"""Corner refinement in the board frame: the flattening of the squares' levels."""

import cv2
import numpy as np
import pytest

from services.calibration.frontal import flatten_squares, refine_corners_frontal
from services.formats.board import ChessboardSpec
from services.simulation.boards import render_board

BOARD = ChessboardSpec(type="chessboard", inner_corners=(9, 6), square_mm=20.0)
K = np.array([[400.0, 0.0, 160.3], [0.0, 400.0, 127.8], [0.0, 0.0, 1.0]])
DIST = np.array([-0.2, 0.1, 0.0, 0.0, 0.0])


def test_flattening_makes_every_light_square_one_and_every_dark_square_zero():
    objects = BOARD.object_points()
    per_mm, low = 1.5, objects[:, :2].min(axis=0) - BOARD.square_mm
    height, width = (np.array([7, 10]) * BOARD.square_mm * per_mm).astype(int) + 1
    v, u = np.mgrid[0:height, 0:width]
    cells = np.floor((np.column_stack([u.ravel(), v.ravel()]) / per_mm + low) / BOARD.square_mm).astype(int)
    light = (cells.sum(axis=1) % 2 == 1).reshape(height, width)
    glow = 0.9 * np.exp(-((u - width / 2) ** 2 + (v - height / 2) ** 2) / (0.8 * width) ** 2)  # a heater's fall-off
    frontal = np.where(light, 0.1 + glow, 0.1 + 0.05 * u / width).astype(np.float32)
    flat = flatten_squares(frontal, objects, low, per_mm, BOARD.square_mm)
    inside = np.zeros_like(light)
    side = int(BOARD.square_mm * per_mm)
    for y0 in range(0, height - side, side):
        for x0 in range(0, width - side, side):
            inside[y0 + side // 4:y0 + 3 * side // 4, x0 + side // 4:x0 + 3 * side // 4] = True
    assert np.ptp(frontal[light & inside]) > 0.3  # the light squares differed
    np.testing.assert_allclose(flat[light & inside], 1.0, atol=0.06)
    np.testing.assert_allclose(flat[~light & inside], 0.0, atol=0.03)


@pytest.mark.parametrize("tilt", [0.3, 0.7])
def test_flattening_brings_hollow_board_corners_closer_to_the_truth(tilt):
    """Noise-free hollow heated board: the heater's fall-off biases the saddle points; flattened, less."""
    objects = BOARD.object_points()
    R = cv2.Rodrigues(np.array([0.6 * tilt, 0.8 * tilt, 0.1]))[0]
    t = np.array([0.0, 0.0, 450.0]) - R @ objects.mean(axis=0)
    image = render_board(BOARD, K, DIST, R, t, (320, 256), modality="infrared", blur_sigma=1.0, supersample=4)
    truth = cv2.projectPoints(objects, cv2.Rodrigues(R)[0], t, K, DIST)[0].reshape(-1, 2)
    start = truth + np.random.default_rng(0).normal(0.0, 0.2, truth.shape)
    error = {}
    for flatten in (False, True):
        refined = refine_corners_frontal(image, objects, start, K, DIST, R, t, BOARD.square_mm, 0.45, flatten=flatten)
        error[flatten] = np.sqrt(np.mean(np.sum((refined - truth) ** 2, axis=1)))
    assert error[True] < 0.9 * error[False]


def test_flattening_leaves_an_evenly_lit_visible_board_unchanged():
    objects = BOARD.object_points()
    R = cv2.Rodrigues(np.array([0.3, 0.4, 0.1]))[0]
    t = np.array([0.0, 0.0, 450.0]) - R @ objects.mean(axis=0)
    image = render_board(BOARD, K, DIST, R, t, (320, 256), blur_sigma=1.0, supersample=4)
    truth = cv2.projectPoints(objects, cv2.Rodrigues(R)[0], t, K, DIST)[0].reshape(-1, 2)
    plain, flat = (refine_corners_frontal(image, objects, truth, K, DIST, R, t, BOARD.square_mm, 0.45, flatten=f)
                   for f in (False, True))
    np.testing.assert_allclose(flat, plain, atol=2e-3)
