import numpy as np
import pytest

from services.structured_light.hdr import merge_exposures


def test_each_pixel_averages_its_unsaturated_exposures_weighted_by_exposure_time():
    rate = np.array([[0.1, 1.0, 3.0]])  # grey levels per microsecond
    exposures = [1000.0, 1000.0, 4000.0]
    stacks = np.stack([np.minimum(np.rint(rate * t), 4095)[None].repeat(2, axis=0) for t in exposures])
    stacks[1, :, 0, 0] += 10  # the repeat reads the first pixel 10 higher: weight 1000 of 6000 us
    merged, saturation = merge_exposures(stacks.astype(np.uint16), exposures, 4095)
    assert saturation == 4 * 4095
    # units of the 4 ms exposure: (100 + 110 + 400) / 6 ms, 6000 / 6 ms, (3000 + 3000) / 2 ms (4 ms saturates)
    np.testing.assert_array_equal(merged[0, 0], [407, 4000, 12000])


def test_repeats_of_one_exposure_reduce_the_shot_noise_by_their_number():
    rng = np.random.default_rng(0)
    electrons = 2000.0  # a glowing pixel, shot-noise limited
    stacks = rng.poisson(electrons, size=(4, 1, 200, 200)).astype(np.uint16)
    merged, _ = merge_exposures(stacks, [100.0] * 4, 4095)
    assert np.std(merged) == pytest.approx(np.sqrt(electrons / 4), rel=0.05)


def test_each_pixel_takes_its_longest_unsaturated_exposure_scaled():
    scene = np.array([[100.0, 1000.0, 6000.0]])  # grey levels per millisecond
    exposures = [0.5, 2.0]
    stacks = np.stack([np.minimum(np.rint(scene * t), 4095)[None].repeat(3, axis=0) for t in exposures])
    merged, saturation = merge_exposures(stacks.astype(np.uint16), exposures, 4095)
    assert saturation == 4 * 4095
    np.testing.assert_array_equal(merged[0, 0], [200, 2000, 12000])  # units of the 2 ms exposure


def test_a_pixel_saturated_at_every_exposure_reads_the_merged_saturation():
    stacks = np.full((2, 3, 1, 2), 4095, dtype=np.uint16)
    stacks[:, :, 0, 1] = [[10, 10, 10], [40, 40, 40]]
    merged, saturation = merge_exposures(stacks, [1.0, 4.0], 4095)
    assert np.all(merged[:, 0, 0] == saturation) and np.all(merged[:, 0, 1] == 40)


def test_the_merge_fits_sixteen_bits():
    stacks = np.full((2, 1, 1, 1), 100, dtype=np.uint16)
    merged, saturation = merge_exposures(stacks, [1.0, 64.0], 4095)
    assert saturation <= 65535 and merged.dtype == np.uint16


def test_bad_exposures_are_refused():
    with pytest.raises(ValueError, match="one exposure time each"):
        merge_exposures(np.zeros((2, 1, 1, 1), np.uint16), [1.0], 255)
    with pytest.raises(ValueError, match="must be positive"):
        merge_exposures(np.zeros((1, 1, 1, 1), np.uint16), [0.0], 255)
