import numpy as np
import pytest

from services.fusion.colormap import UNSEEN_COLOR, colormap_lut, temperature_colors


def test_lookup_is_computed_once_read_only_and_perceptually_ordered():
    lut = colormap_lut("inferno")
    assert lut is colormap_lut("inferno")
    assert lut.shape == (256, 3) and lut.dtype == np.uint8
    assert not lut.flags.writeable
    luminance = lut @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(luminance) > -1.0)  # inferno brightens monotonically (to rounding)


def test_ends_of_the_range_map_to_the_ends_of_the_lut_and_nan_to_grey():
    colors = temperature_colors(np.array([100.0, np.nan, 1100.0, 600.0]))
    lut = colormap_lut("inferno")
    np.testing.assert_array_equal(colors[0], lut[0])
    np.testing.assert_array_equal(colors[2], lut[255])
    np.testing.assert_array_equal(colors[1], UNSEEN_COLOR)
    np.testing.assert_array_equal(colors[3], lut[128])


def test_explicit_range_clips_and_all_nan_is_grey():
    colors = temperature_colors(np.array([0.0, 2000.0]), vmin=500, vmax=1000, name="turbo")
    np.testing.assert_array_equal(colors, colormap_lut("turbo")[[0, 255]])
    assert np.all(temperature_colors(np.full(3, np.nan)) == UNSEEN_COLOR)


def test_unknown_colormap_is_refused():
    with pytest.raises(ValueError, match="Unknown colour map"):
        temperature_colors(np.ones(2), name="no-such-map")
