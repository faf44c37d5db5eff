import cv2
import numpy as np
import pytest

from services.registration.preprocess import (
    PREPROCESSING,
    clahe,
    gradient_magnitude,
    invert_equalize,
    preprocess,
    to_uint8,
)


def _ramp() -> np.ndarray:
    return np.tile(np.linspace(0, 200, 128), (96, 1)).astype(np.uint8)


def test_to_uint8_stretches_16_bit_counts_and_keeps_8_bit():
    counts = np.tile(np.linspace(1000, 9000, 100), (50, 1)).astype(np.uint16)
    stretched = to_uint8(counts)
    assert stretched.dtype == np.uint8
    assert stretched.min() == 0 and stretched.max() == 255
    assert np.all(np.diff(stretched[0].astype(int)) >= 0)
    image = _ramp()
    assert to_uint8(image) is image


def test_paper_preprocessing_inverts_and_flattens_the_histogram():
    result = invert_equalize(_ramp())
    assert result.dtype == np.float32 and 0.0 <= result.min() and result.max() <= 1.0
    assert result[0, 0] > result[0, -1]  # dark left end became bright
    counts, _ = np.histogram(result, bins=4, range=(0, 1))
    assert counts.min() > 0.15 * result.size  # about a quarter of the pixels in each quarter


def test_clahe_raises_local_contrast_of_a_faint_pattern():
    rng = np.random.default_rng(0)
    faint = (120 + 5 * rng.random((128, 128))).astype(np.uint8)
    result = clahe(faint)
    assert result.std() > faint.std() / 255.0


def test_gradient_magnitude_peaks_on_the_edge_and_ignores_polarity():
    step = np.zeros((64, 64), np.uint8)
    step[:, 32:] = 200
    magnitude = gradient_magnitude(step)
    assert set(np.argmax(magnitude, axis=1)) <= {31, 32}
    np.testing.assert_allclose(gradient_magnitude(255 - step), magnitude, atol=1e-6)


def test_gradient_magnitude_is_the_same_to_the_bit_from_one_call_to_the_next():
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.integers(0, 256, (300, 500)).astype(np.uint8), (0, 0), 2.0)
    results, allocations = set(), []
    for size in rng.integers(1, 200, 60):  # allocations of odd sizes shift where the next arrays start in memory
        allocations.append(np.empty(int(size), np.float32))
        results.add(gradient_magnitude(image).tobytes())
    assert len(results) == 1


@pytest.mark.parametrize("method", PREPROCESSING)
def test_every_method_returns_unit_range_float32_of_the_same_shape(method):
    result = preprocess(_ramp(), method, invert=True)
    assert result.shape == (96, 128) and result.dtype == np.float32
    assert 0.0 <= result.min() and result.max() <= 1.0


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: preprocess(_ramp(), "sharpen"), "Unknown preprocessing"),
        (lambda: to_uint8(np.zeros((4, 4, 3))), "2-D"),
        (lambda: to_uint8(np.full((32, 32), np.nan)), "no finite pixel"),
        (lambda: clahe(_ramp(), clip_limit=0.0), "positive clip limit"),
        (lambda: gradient_magnitude(_ramp(), sigma=-1.0), "non-negative"),
    ],
)
def test_bad_input_is_refused_with_a_sentence(call, message):
    with pytest.raises(ValueError, match=message):
        call()
