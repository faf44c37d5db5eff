import numpy as np

from services.registration.models import apply_homography
from services.registration.synthetic_pairs import (
    INFRARED_LEVELS,
    infrared_from_visible,
    moved_image,
    moved_view,
    random_transform,
    render_scene_pair,
)


def test_random_transforms_stay_within_the_requested_ranges():
    rng = np.random.default_rng(0)
    centre = np.array([[159.5, 127.5]])
    for _ in range(50):
        matrix = random_transform(rng, (320, 256), (1024, 768), 3.0, max_shift=40.0, max_angle=5.0,
                                  max_scale_change=0.1)
        scale = np.sqrt(np.linalg.det(matrix[:2, :2]))
        angle = np.degrees(np.arctan2(matrix[1, 0], matrix[0, 0]))
        shift = apply_homography(matrix, centre)[0] - [511.5, 383.5]
        assert 2.7 <= scale <= 3.3 and abs(angle) <= 5.0 and np.all(np.abs(shift) <= 40.0)


def test_rendered_pair_has_the_requested_sizes_and_bit_depths():
    rng = np.random.default_rng(1)
    matrix = random_transform(rng, (320, 256), (1024, 768), 3.0)
    visible, infrared = render_scene_pair(rng, matrix)
    assert visible.shape == (768, 1024) and visible.dtype == np.uint8
    assert infrared.shape == (256, 320) and infrared.dtype == np.uint16
    assert infrared.max() <= INFRARED_LEVELS and infrared.max() > 0.5 * INFRARED_LEVELS  # hot parts in view


def test_infrared_from_visible_is_a_negative_of_the_photograph_seen_through_the_matrix():
    rng = np.random.default_rng(2)
    visible = np.zeros((480, 640), np.uint8)
    visible[100:300, 200:500] = 250
    matrix = np.array([[2.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    infrared = infrared_from_visible(rng, visible, matrix, blobs=0, noise=0.0).astype(float)
    assert infrared[100, 175] < infrared[20, 20]  # inside the bright rectangle (visible 350, 200): cold
    assert infrared[100, 95] > infrared[100, 105]  # the rectangle's left edge sits at infrared x = 100


def test_moved_view_stays_inside_the_image_and_knows_its_move():
    rng = np.random.default_rng(4)
    image = np.arange(300 * 400, dtype=np.float32).reshape(300, 400)  # value = 400 y + x
    moved, view_to_original = moved_view(rng, image, max_shift=30.0, max_angle=4.0, scale_range=(0.93, 1.07))
    height, width = moved.shape
    assert 0.5 * 400 <= width <= 0.9 * 400 and abs(height / width - 0.75) < 0.01
    ys, xs = np.mgrid[0:height, 0:width]
    original = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]).T @ view_to_original.T
    assert original[:, 0].min() >= 1.0 and original[:, 0].max() <= 398.0 and original[:, 1].max() <= 298.0
    np.testing.assert_allclose(moved.ravel(), 400.0 * original[:, 1] + original[:, 0], atol=0.05)
    forward = np.linalg.inv(view_to_original)
    scale = np.sqrt(np.linalg.det(forward[:2, :2]))
    assert 0.93 <= scale <= 1.07 and abs(np.degrees(np.arctan2(forward[1, 0], forward[0, 0]))) <= 4.0


def test_moved_image_keeps_its_size_masks_what_the_move_brings_in_and_knows_its_move():
    image = np.arange(300 * 400, dtype=np.float32).reshape(300, 400)  # value = 400 y + x
    moved, valid, moved_to_original = moved_image(np.random.default_rng(4), image)
    assert moved.shape == image.shape and moved.dtype == image.dtype and valid.shape == image.shape
    assert 0.5 < valid.mean() < 1.0  # a move of up to 30 px, 4 degrees and 7 % brings some border in
    ys, xs = np.mgrid[0:300, 0:400]
    original = np.stack([xs.ravel(), ys.ravel(), np.ones(xs.size)]).T @ moved_to_original.T
    inside = ((original[:, 0] >= 0.0) & (original[:, 0] <= 399.0) & (original[:, 1] >= 0.0)
              & (original[:, 1] <= 299.0))
    np.testing.assert_array_equal(valid.ravel(), inside)
    np.testing.assert_allclose(moved.ravel()[inside], (400.0 * original[:, 1] + original[:, 0])[inside], atol=0.05)
    _, view_to_original = moved_view(np.random.default_rng(4), image)  # the same draws: the same move
    np.testing.assert_allclose(moved_to_original[:2, :2], view_to_original[:2, :2], rtol=1e-12)
