"""The pixels without data found from the image itself: a border a move or a crop brought in, not the scene."""

import cv2
import numpy as np
import pytest

from services.registration.borders import data_mask
from services.registration.synthetic_pairs import moved_image
from tests.registration.conftest import scene_pair


def _scene() -> np.ndarray:
    return scene_pair(21)[1]  # a rendered 320x256 14-bit infrared image, no constant border


def test_an_image_without_a_constant_border_is_all_data():
    assert data_mask(_scene()) is None


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_border_a_move_brought_in_is_found_and_nothing_of_the_scene_is_lost(seed):
    infrared = _scene()
    moved, valid, _ = moved_image(np.random.default_rng(seed), infrared)
    mask = data_mask(moved)
    assert mask is not None
    # every pixel whose bilinear support lies inside the original is data, but for the one blended pixel
    # next to the border (which the detection counts without data too)
    near_border = cv2.dilate((~valid).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert mask[~near_border].all()
    # every pixel the move brought in is found: none of them is counted as data
    assert not mask[~valid & (moved == 0)].any()


@pytest.mark.parametrize("value", [0, 255])
def test_constant_bars_of_a_crop_or_an_export_are_found(value):
    image = (_scene() // 64).astype(np.uint8)
    image[:, :20] = value  # a bar on the left and a letterbox at the bottom
    image[230:, :] = value
    mask = data_mask(image)
    assert not mask[:, :20].any() and not mask[230:].any()
    assert mask[:229, 21:].all()  # the rest is data up to the pixel next to the bars


def test_a_constant_region_of_the_scene_inside_the_outline_keeps_its_edges():
    # a saturated sky touches the top border and reaches down between two roofs, with data on both sides:
    # only what lies above the convex outline of the rest is without data
    image = np.tile(np.linspace(10, 250, 320), (256, 1)).astype(np.uint8)
    rows, columns = np.mgrid[0:256, 0:320]
    roofs = rows < np.minimum(40 + 0.8 * np.minimum(np.abs(columns - 80), np.abs(columns - 240)), 150)
    image[roofs] = 0
    mask = data_mask(image)
    assert mask[100, 160] and mask[60, 160]  # the sky between the roofs, under their peaks' outline, is data
    assert not mask[5, 160]  # the sky above the outline is not: nothing there to register


def test_a_constant_image_has_no_data_to_separate():
    assert data_mask(np.full((100, 120), 7, np.uint16)) is None


def test_a_non_grey_image_is_refused():
    with pytest.raises(ValueError, match="2-D grey image"):
        data_mask(np.zeros((10, 10, 3)))
