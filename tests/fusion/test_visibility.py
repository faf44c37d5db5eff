import numpy as np
import pytest

from services.fusion.visibility import (depth_gradient, fill_empty_pixels, nearest_depth_around, nearest_pixel_index,
                                       splat_nearest, within_tolerance)


def _z_buffer(pixels, depth, width, height):
    """The z-buffer as the fusion makes it: splats at the nearest pixels, empty pixels filled from their 3x3."""
    buffer = np.full(width * height, np.inf)
    splat_nearest(buffer, nearest_pixel_index(pixels[:, 0], pixels[:, 1], width, height), depth)
    return fill_empty_pixels(buffer.reshape(height, width))


def test_buffer_keeps_the_nearest_depth_per_pixel_and_fills_isolated_holes():
    pixels = np.array([[1.2, 1.4], [0.8, 0.6], [3.0, 3.0], [10.0, 1.0], [np.nan, 0.0]])
    depth = np.array([500.0, 400.0, 600.0, 100.0, 50.0])
    buffer = _z_buffer(pixels, depth, width=6, height=5)
    assert buffer[1, 1] == 400.0
    assert buffer[3, 3] == 600.0
    assert buffer[2, 2] == 400.0  # empty, takes its nearest 3x3 neighbour
    assert np.isinf(buffer[4, 0])  # far from every point
    assert np.all(buffer[:, 5] >= 400.0)  # the point outside the image is not drawn


def test_hidden_points_fail_the_depth_test_and_seen_ones_pass():
    pixels = np.array([[2.0, 2.0], [2.1, 1.9], [4.0, 4.0]])
    depth = np.array([300.0, 500.0, 500.0])
    buffer = _z_buffer(pixels, depth, 8, 8)
    index = nearest_pixel_index(pixels[:, 0], pixels[:, 1], 8, 8)
    np.testing.assert_array_equal(within_tolerance(index, depth, buffer.ravel(), np.full(3, 2.0)), [True, False, True])


def test_depth_gradient_of_a_tilted_plane_matches_finite_differences():
    focal = 400.0
    normal = np.array([np.sin(0.6), 0.0, -np.cos(0.6)])
    point = np.array([30.0, -20.0, 600.0])
    gradient = depth_gradient(point[None], normal[None], focal, np.deg2rad(80))[0]
    # depth along the plane through ``point`` at the pixel one step to the right
    x, y = point[0] / point[2], point[1] / point[2]
    ray = np.array([x + 1 / focal, y, 1.0])
    depth_next = (normal @ point) / (normal @ ray)
    assert gradient == pytest.approx(abs(depth_next - point[2]), rel=2e-3)


def test_unknown_normals_use_the_angle_limit_and_window_minimum():
    gradient = depth_gradient(np.array([[0.0, 0.0, 380.0]]), np.full((1, 3), np.nan), 380.0, np.deg2rad(45))
    assert gradient[0] == pytest.approx(1.0)
    buffer = np.full((5, 5), 10.0)
    buffer[0, 0] = 1.0
    around = nearest_depth_around(buffer, 1)
    assert around[1, 1] == 1.0 and around[2, 2] == 10.0


def test_footprint_radius_covers_the_stencil_the_pixel_and_the_blur():
    from services.fusion.visibility import footprint_radius

    assert footprint_radius(0.0) == 2  # the bilinear stencil's corner 1 px away and half its pixel
    assert footprint_radius(0.0, stencil_px=0.0) == 1
    assert footprint_radius(0.6) == 3 and footprint_radius(1.0) == 4 and footprint_radius(1.0, 0.0) == 3
    with pytest.raises(ValueError, match="blur"):
        footprint_radius(-1.0)


def test_background_depth_sees_empty_space_beyond_an_outline_but_not_gaps_between_splats():
    from services.fusion.visibility import background_depth

    buffer = np.full((40, 60), np.inf)
    buffer[10:30, 10:50] = 500.0
    buffer[20, 30] = np.inf  # a gap between splats
    buffer[15, 12] = np.inf
    far = background_depth(buffer, 2)
    assert far[20, 30] == 500.0 and far[15, 12] == 500.0  # gaps add nothing
    assert far[20, 20] == 500.0
    assert np.isinf(far[11, 20]) and np.isinf(far[20, 48])  # within 2 px of the outline: empty space
    buffer[:, 50:] = 700.0  # a wall behind, on the right
    far = background_depth(buffer, 2)
    assert far[20, 48] == 700.0 and far[20, 40] == 500.0
    edge = np.full((10, 10), 500.0)
    assert np.isinf(background_depth(edge, 2)[5, 0]) and background_depth(edge, 2)[5, 5] == 500.0  # beyond the image


def test_background_depth_ignores_a_far_side_showing_through_gaps_but_not_a_wide_one():
    from services.fusion.visibility import background_depth

    # the near side of a merged all-round cloud (500 mm) with its far side (590 mm) behind it everywhere
    buffer = np.full((40, 60), np.inf)
    buffer[10:30, 10:50] = 590.0
    near = buffer.copy()
    near[12:28, 12:48] = 500.0
    through = near.copy()
    through[20, 30] = through[21, 31] = through[15, 20] = 590.0  # one-pixel gaps in the near side
    assert background_depth(through, 2)[20, 30] == background_depth(near, 2)[20, 30] == 500.0
    np.testing.assert_array_equal(background_depth(through, 2), background_depth(near, 2))
    wide = near.copy()
    wide[18:26, 26:34] = 590.0  # a window of the far side wider than the footprint is a farther surface
    assert background_depth(wide, 2)[22, 30] == 590.0 and background_depth(wide, 2)[22, 24] == 590.0
    # a smaller step than depth_step_mm is the surface's own relief, not a gap
    relief = near.copy()
    relief[20, 30] = 501.0
    assert background_depth(relief, 2)[20, 30] == 501.0
