import numpy as np
import pytest

from services.registration.mutual_information import (
    MOVING_SUBBINS,
    information_from_histogram,
    joint_histogram,
    moving_window,
    mutual_information,
    quantize,
    windowed_joint_histogram,
)


def _hard_entropy(labels: np.ndarray) -> float:
    _, counts = np.unique(labels, return_counts=True, axis=0)
    p = counts / counts.sum()
    return float(-(p * np.log2(p)).sum())


def test_histogram_of_bin_centred_values_equals_the_hard_histogram():
    rng = np.random.default_rng(0)
    fixed = rng.integers(0, 8, size=(40, 50)).astype(np.float32)
    moving = rng.integers(0, 8, size=(40, 50)).astype(np.float32)
    fixed[0, 0], moving[0, 0] = 7, 7  # both span 0..7, so quantising to 8 bins keeps the integers
    expected, _, _ = np.histogram2d(fixed.ravel(), moving.ravel(), bins=8, range=[[-0.5, 7.5], [-0.5, 7.5]])
    np.testing.assert_allclose(joint_histogram(fixed, moving, bins=8), expected)


def test_fractional_values_are_spread_over_the_four_nearest_cells_with_bilinear_weights():
    """The fixed values exactly; the moving ones rounded to 1/MOVING_SUBBINS of a bin (the module's docstring)."""
    rng = np.random.default_rng(5)
    fixed = (rng.random(300) * 7).astype(np.float32)
    moving = (rng.random(300) * 7).astype(np.float32)
    fixed[:20] = -1.0  # invalid samples are skipped
    moving[[0, 30]] = 7.0  # the top value goes wholly to the top bin
    expected = np.zeros((8, 8))
    for a, b in zip(fixed, np.rint(moving * MOVING_SUBBINS) / MOVING_SUBBINS):
        if a < 0:
            continue
        row, column = min(int(a), 6), min(int(b), 6)
        up, right = a - row, b - column
        for cell_row, row_weight in ((row, 1 - up), (row + 1, up)):
            for cell_column, column_weight in ((column, 1 - right), (column + 1, right)):
                expected[cell_row, cell_column] += row_weight * column_weight
    np.testing.assert_allclose(windowed_joint_histogram(fixed, moving_window(moving, 8), 8), expected, atol=1e-5)


def test_mi_matches_the_entropy_definition_on_discrete_images():
    rng = np.random.default_rng(1)
    fixed = rng.integers(0, 4, size=(64, 64))
    moving = (fixed + (rng.random(fixed.shape) < 0.2)) % 4
    mi, nmi = mutual_information(fixed, moving, bins=4)
    h_fixed, h_moving = _hard_entropy(fixed.ravel()), _hard_entropy(moving.ravel())
    h_joint = _hard_entropy(np.stack([fixed.ravel(), moving.ravel()], axis=1))
    assert mi == pytest.approx(h_fixed + h_moving - h_joint, rel=1e-9)
    assert nmi == pytest.approx((h_fixed + h_moving) / h_joint, rel=1e-9)


def test_mi_of_an_image_with_a_bijective_remapping_of_itself_is_its_entropy():
    rng = np.random.default_rng(2)
    fixed = rng.integers(0, 16, size=(100, 100))
    fixed[0, 0], fixed[0, 1] = 0, 15
    inverted = 15 - fixed
    mi, nmi = mutual_information(fixed, inverted, bins=16)
    assert mi == pytest.approx(_hard_entropy(fixed.ravel()), rel=1e-9)
    assert nmi == pytest.approx(2.0)


def test_independent_images_have_almost_no_information_in_common():
    rng = np.random.default_rng(3)
    mi, nmi = mutual_information(rng.random((200, 200)), rng.random((200, 200)), bins=16)
    assert 0.0 <= mi < 0.02
    assert 1.0 <= nmi < 1.005


def test_log_base_scales_mi_but_not_nmi():
    rng = np.random.default_rng(4)
    fixed = rng.random((80, 80))
    moving = fixed**2 + 0.1 * rng.random((80, 80))
    bits, nmi_bits = mutual_information(fixed, moving, log_base=2.0)
    nats, nmi_nats = mutual_information(fixed, moving, log_base=np.e)
    assert nats == pytest.approx(bits * np.log(2.0))
    assert nmi_nats == pytest.approx(nmi_bits)


def test_mask_and_non_finite_pixels_are_left_out():
    rng = np.random.default_rng(5)
    fixed = rng.random((60, 60))
    moving = 1.0 - fixed
    moving_with_nan = moving.copy()
    moving_with_nan[:, :10] = np.nan
    mask = np.ones(fixed.shape, bool)
    mask[:, :10] = False
    assert joint_histogram(fixed, moving_with_nan).sum() == pytest.approx(50 * 60)
    assert mutual_information(fixed, moving_with_nan) == pytest.approx(mutual_information(fixed, moving, mask=mask))


def test_quantize_marks_invalid_pixels_negative_and_spans_the_bins():
    image = np.array([[2.0, 4.0], [6.0, np.nan]])
    scaled = quantize(image, bins=5)
    np.testing.assert_allclose(scaled[0], [0.0, 2.0])
    assert scaled[1, 0] == pytest.approx(4.0)
    assert scaled[1, 1] < 0


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: mutual_information(np.zeros((4, 4)), np.zeros((4, 5))), "same shape"),
        (lambda: mutual_information(np.zeros((4, 4)), np.zeros((4, 4)), bins=1), "at least 2 bins"),
        (lambda: information_from_histogram(np.ones((3, 3)), log_base=1.0), "log base"),
        (lambda: information_from_histogram(np.ones((3, 4))), "square"),
        (lambda: joint_histogram(np.zeros((4, 4)), np.zeros((4, 4)), mask=np.ones((2, 2), bool)), "mask"),
    ],
)
def test_bad_input_is_refused_with_a_sentence(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_empty_histogram_has_zero_information():
    assert information_from_histogram(np.zeros((4, 4))) == (0.0, 1.0)


def test_histograms_against_one_window_do_not_depend_on_the_previous_ones():
    rng = np.random.default_rng(9)
    moving = quantize(rng.random((30, 40)), 8)
    first, second = (quantize(rng.random((30, 40)), 8) for _ in range(2))
    second[:10] = -1.0
    window = moving_window(moving, 8)  # its work arrays are reused by every histogram
    expected = windowed_joint_histogram(first, moving_window(moving, 8), 8)
    windowed_joint_histogram(second, window, 8)
    np.testing.assert_array_equal(windowed_joint_histogram(first, window, 8), expected)


def test_fixed_samples_must_match_the_window():
    window = moving_window(np.zeros((4, 4), np.float32), 8)
    with pytest.raises(ValueError, match="must match the moving window's pixels"):
        windowed_joint_histogram(np.zeros((4, 5), np.float32), window, 8)
