import numpy as np
import pytest

from services.registration.mutual_information import moving_window, quantize
from services.registration.objective import FixedSampler, information, sample_fixed, score


def test_samples_outside_the_fixed_image_are_negative_and_inside_ones_exact():
    fixed = np.arange(100, dtype=np.float32).reshape(10, 10)
    shift = np.array([[1.0, 0.0, 5.0], [0.0, 1.0, 2.0], [0.0, 0.0, 1.0]])
    samples = sample_fixed(fixed, shift, 8, 8)
    np.testing.assert_allclose(samples[:8, :5], fixed[2:10, 5:10])
    assert np.all(samples[:, 5:] < 0)


def test_bicubic_samples_are_valid_only_where_their_four_by_four_support_is_inside():
    fixed = np.arange(100, dtype=np.float32).reshape(10, 10)
    shift = np.array([[1.0, 0.0, 4.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])  # half-pixel offsets on both axes
    samples = sample_fixed(fixed, shift, 8, 8, cubic=True)
    # sample (row r, column c) sits at (4.5 + c, 0.5 + r): its support spans columns 4 + c - 1 .. 4 + c + 2
    # and rows r - 1 .. r + 2, so columns c <= 3 and rows 1 <= r <= 7 are inside
    inside = np.zeros((8, 8), bool)
    inside[1:8, :4] = True
    assert np.all(samples[inside] >= 0) and np.all(samples[~inside] < 0)
    # a linear ramp is reproduced exactly by the bicubic kernel
    rows, columns = np.nonzero(inside)
    np.testing.assert_allclose(samples[inside], 10.0 * (rows + 0.5) + (columns + 4.5), rtol=0, atol=1e-3)


@pytest.mark.parametrize("cubic", [False, True])
def test_a_sampler_reused_for_other_matrices_gives_what_a_fresh_sampling_gives(cubic):
    rng = np.random.default_rng(4)
    fixed = rng.random((30, 40)).astype(np.float32)
    sampler = FixedSampler(fixed, 25, 20, cubic)
    matrices = [np.array([[1.0, 0.02, dx], [-0.02, 1.0, dy], [0.0, 0.0, 1.0]]) for dx, dy in ((3.3, 2.1), (17.0, 12.6))]
    matrices.append(np.array([[1.0, 0.0, 2.0], [0.0, 1.0, 1.0], [0.0005, 0.0, 1.0]]))  # perspective, then affine again
    for matrix in matrices + matrices[:1]:
        expected = sample_fixed(fixed, matrix, 25, 20, cubic)
        np.testing.assert_array_equal(sampler(matrix), expected)
    assert np.any(sampler(matrices[1]) < 0) and np.any(sampler(matrices[0]) >= 0)  # the outside marks move too


def test_perspective_matrices_are_sampled_too():
    fixed = np.ones((20, 20), np.float32)
    perspective = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.001, 0.0, 1.0]])
    assert np.all(sample_fixed(fixed, perspective, 10, 10) == 1.0)


def test_score_is_minus_infinity_below_the_minimum_overlap():
    rng = np.random.default_rng(0)
    moving = quantize(rng.random((20, 20)), 8)
    fixed_samples = moving.copy()
    fixed_samples[:, :12] = -1.0  # 40 % overlap
    mi, nmi, weight = information(fixed_samples, moving, 8, 2.0)
    assert weight == pytest.approx(160.0)
    window = moving_window(moving, 8)
    assert information(fixed_samples, window, 8, 2.0) == pytest.approx((mi, nmi, weight))
    assert score(fixed_samples, window, 8, 2.0, "nmi", 0.3) == pytest.approx(nmi)
    assert score(fixed_samples, window, 8, 2.0, "mi", 0.3) == pytest.approx(mi)
    assert score(fixed_samples, window, 8, 2.0, "mi", 0.5) == -np.inf
