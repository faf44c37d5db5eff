import cv2
import numpy as np
import pytest

from services.calibration.corner_window import WINDOW_FRACTIONS, select_corner_window
from services.calibration.corners import DEFAULT_WINDOW_FRACTION, detect_board, refine_corners
from services.simulation.boards import render_board

from .simulated_rig import project

K = np.array([[700.0, 0.0, 320.0], [0.0, 700.0, 240.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.1, 0.05, 0.0, 0.0, 0.0])
SIZE = (640, 480)


def _views(board, count, blur_sigma, seed=0):
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        R = cv2.Rodrigues(rng.uniform(-0.4, 0.4, 3))[0]
        t = np.array([*rng.uniform(-30, 30, 2), rng.uniform(380, 520)]) - R @ board.object_points().mean(axis=0)
        image = render_board(board, K, DIST, R, t, SIZE, blur_sigma=blur_sigma, noise_sigma=2.0, rng=rng)
        detection = detect_board(image, board)
        views.append((image, detection, project(board, K, DIST, R, t)[detection.ids]))
    return views


@pytest.fixture(scope="module")
def blurred_views(chessboard_9x6):
    return _views(chessboard_9x6, 6, blur_sigma=1.5)


def test_the_window_of_lowest_held_out_error_is_chosen(chessboard_9x6, blurred_views):
    images = [image for image, _, _ in blurred_views]
    points = [detection.image_points for _, detection, _ in blurred_views]
    objects = [chessboard_9x6.object_points()[detection.ids] for _, detection, _ in blurred_views]
    selection = select_corner_window(images, points, objects, SIZE)
    assert set(selection.held_out_rms) == set(WINDOW_FRACTIONS)
    assert selection.held_out_rms[selection.fraction] == min(selection.held_out_rms.values())
    assert str(selection.fraction) in selection.reason
    # The chosen window's corners are those refined with it.
    np.testing.assert_allclose(selection.image_points[3], refine_corners(images[3], points[3], selection.fraction))


def test_the_held_out_error_tracks_the_true_corner_error(chessboard_9x6, blurred_views):
    """Ground truth: the window chosen without it locates the corners nearly as well as the best one."""
    images = [image for image, _, _ in blurred_views]
    points = [detection.image_points for _, detection, _ in blurred_views]
    objects = [chessboard_9x6.object_points()[detection.ids] for _, detection, _ in blurred_views]
    truths = np.concatenate([truth for _, _, truth in blurred_views])

    def true_rms(fraction):
        refined = np.concatenate([refine_corners(image, p, fraction) for image, p in zip(images, points)])
        return np.sqrt(np.mean(np.sum((refined - truths) ** 2, axis=1)))

    errors = {fraction: true_rms(fraction) for fraction in WINDOW_FRACTIONS}
    chosen = select_corner_window(images, points, objects, SIZE).fraction
    assert errors[chosen] <= 1.15 * min(errors.values())
    assert errors[chosen] < errors[max(errors, key=errors.get)]


def test_too_few_views_keep_the_default_window(chessboard_9x6, blurred_views):
    three = blurred_views[:3]
    selection = select_corner_window([v[0] for v in three], [v[1].image_points for v in three],
                                     [chessboard_9x6.object_points()[v[1].ids] for v in three], SIZE)
    assert selection.fraction == DEFAULT_WINDOW_FRACTION and selection.held_out_rms == {}
    assert "too few" in selection.reason


def test_views_without_their_corners_are_refused(chessboard_9x6, blurred_views):
    with pytest.raises(ValueError, match="Every view needs its image, corners and board points"):
        select_corner_window([blurred_views[0][0]], [], [], SIZE)


def test_a_window_reaching_the_next_corner_is_refused(blurred_views):
    image, detection, _ = blurred_views[0]
    with pytest.raises(ValueError, match="between 0 and 0.5"):
        refine_corners(image, detection.image_points, 0.6)
