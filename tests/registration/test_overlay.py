import numpy as np
import pytest

from services.registration.overlay import checkerboard_blend, fused_overlay


def _images() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    visible = rng.integers(0, 256, size=(120, 160), dtype=np.uint8)
    infrared = np.full((30, 40), 1000, np.uint16)
    infrared[:, 20:] = 3000
    return visible, infrared


def _half_scale_at(x: float, y: float) -> np.ndarray:
    return np.array([[2.0, 0.0, x], [0.0, 2.0, y], [0.0, 0.0, 1.0]])


def test_overlay_blends_inside_the_infrared_footprint_only():
    visible, infrared = _images()
    overlay = fused_overlay(visible, infrared, _half_scale_at(10.0, 20.0), alpha=1.0)
    assert overlay.shape == visible.shape and overlay.dtype == np.uint8
    np.testing.assert_array_equal(overlay[:19], visible[:19])  # the footprint starts half a pixel above row 20
    np.testing.assert_array_equal(overlay[:, :9], visible[:, :9])
    assert overlay[40, 20] == 0 and overlay[40, 70] == 255  # cold and hot halves, equalised


def test_overlay_with_zero_alpha_is_the_visible_image():
    visible, infrared = _images()
    np.testing.assert_array_equal(fused_overlay(visible, infrared, _half_scale_at(0.0, 0.0), alpha=0.0), visible)


def test_checkerboard_alternates_tiles_inside_the_footprint():
    visible, infrared = _images()
    board = checkerboard_blend(visible, infrared, _half_scale_at(0.0, 0.0), tile=10)
    np.testing.assert_array_equal(board[:10, :10], visible[:10, :10])
    assert np.all(board[2:8, 12:18] == 0)  # second tile, cold half of the infrared image
    np.testing.assert_array_equal(board[70:, :], visible[70:, :])  # below the footprint


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda v, i: fused_overlay(v, i, np.zeros((3, 3))), "invertible"),
        (lambda v, i: fused_overlay(v, i, np.eye(3), alpha=2.0), "alpha"),
        (lambda v, i: checkerboard_blend(v, i, np.eye(3), tile=0), "tile"),
    ],
)
def test_bad_input_is_refused(call, message):
    with pytest.raises(ValueError, match=message):
        call(*_images())
