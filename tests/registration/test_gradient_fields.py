import cv2
import numpy as np
import pytest

from services.registration.gradient_fields import (
    FieldTemplate,
    SampledFieldSimilarity,
    gradient_epsilon,
    normalized_gradient_field,
    sampled_tensor_similarity,
    tensor_similarity_map,
)

pytestmark = pytest.mark.integration


def _texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 2.0)


def test_field_is_a_unit_vector_on_strong_edges_and_fades_on_flat_ground():
    image = np.zeros((20, 20), np.float32)
    image[:, 10:] = 1.0
    nx, ny = normalized_gradient_field(image, 0.01)
    assert nx[10, 9] == pytest.approx(0.5 / np.hypot(0.5, 0.01)) and abs(ny[10, 9]) < 1e-6
    assert np.all(nx[:, :8] == 0.0) and np.all(nx[:, 12:] == 0.0)


def test_similarity_ignores_contrast_polarity_and_drops_when_misaligned():
    image = _texture((60, 80), 0)
    epsilon = gradient_epsilon(image)
    nx, ny = normalized_gradient_field(image, epsilon)
    same, count = sampled_tensor_similarity(1.0 - image, epsilon, nx, ny)
    assert same == pytest.approx(1.0, abs=1e-5) and count == 58 * 78
    shifted, _ = sampled_tensor_similarity(np.roll(image, 3, axis=1), epsilon, nx, ny)
    assert shifted < 0.6 * same


def test_a_similarity_reused_for_other_samples_gives_what_a_fresh_one_gives():
    image = _texture((50, 60), 6)
    epsilon = gradient_epsilon(image)
    nx, ny = normalized_gradient_field(image, epsilon)
    similarity = SampledFieldSimilarity(epsilon, nx, ny)  # its work arrays are overwritten by every call
    partly_outside = np.roll(image, 2, axis=0)
    partly_outside[:, :7] = -1.0e4
    for samples in (image, partly_outside, np.roll(image, 5, axis=1), image):
        assert similarity(samples) == sampled_tensor_similarity(samples, epsilon, nx, ny)
    assert similarity(partly_outside)[1] < similarity(image)[1]


def test_pixels_next_to_the_outside_are_left_out():
    image = _texture((40, 40), 1)
    samples = image.copy()
    samples[:, :10] = -1.0e4
    nx, ny = normalized_gradient_field(image, gradient_epsilon(image))
    value, count = sampled_tensor_similarity(samples, gradient_epsilon(image), nx, ny)
    assert count == 38 * (38 - 10) and value == pytest.approx(1.0, abs=1e-5)


def test_similarity_map_peaks_at_the_true_offset_and_agrees_with_the_sampled_similarity():
    canvas = _texture((70, 90), 2)
    epsilon = gradient_epsilon(canvas)
    moving = canvas[9:59, 4:74]
    fx, fy = normalized_gradient_field(canvas, epsilon)
    valid = np.ones_like(canvas)
    mx, my = normalized_gradient_field(moving, epsilon)
    values = tensor_similarity_map(fx, fy, valid, FieldTemplate(mx, my, canvas.shape), 0.5 * moving.size)
    assert np.unravel_index(np.argmax(values), values.shape) == (9, 4)
    windowed_x, windowed_y = fx[2:52, 6:76], fy[2:52, 6:76]
    expected = np.sum((windowed_x * mx + windowed_y * my) ** 2) / np.sqrt(
        np.sum((windowed_x**2 + windowed_y**2) ** 2) * np.sum((mx**2 + my**2) ** 2))
    assert values[2, 6] == pytest.approx(expected, rel=1e-3) and expected < values[9, 4]


def test_too_little_overlap_gives_minus_infinity():
    canvas = _texture((40, 40), 3)
    valid = np.zeros_like(canvas)
    valid[:, :5] = 1.0
    fx, fy = normalized_gradient_field(canvas, 0.01)
    mx, my = normalized_gradient_field(canvas[:30, :30], 0.01)
    values = tensor_similarity_map(fx * valid, fy * valid, valid, FieldTemplate(mx, my, canvas.shape), 0.3 * 900)
    assert np.isneginf(values[0, 10])


def test_a_canvas_smaller_than_the_template_or_of_another_shape_is_refused():
    field = np.zeros((30, 30), np.float32)
    with pytest.raises(ValueError, match="must be at least the moving field's shape"):
        FieldTemplate(field, field, (20, 40))
    with pytest.raises(ValueError, match="must have the template's canvas shape"):
        tensor_similarity_map(field, field, field, FieldTemplate(field[:10, :10], field[:10, :10], (20, 20)), 1.0)


def test_epsilon_must_be_positive():
    with pytest.raises(ValueError, match="epsilon must be positive"):
        normalized_gradient_field(np.zeros((5, 5)), 0.0)


def test_the_similarity_does_not_depend_on_where_its_arrays_sit_in_memory():
    image = _texture((50, 60), 6)
    epsilon = gradient_epsilon(image)
    nx, ny = normalized_gradient_field(image, epsilon)
    partly_outside = np.roll(image, 2, axis=0)
    partly_outside[:, :7] = -1.0e4
    values, spacers = set(), []
    for size in range(64):  # each spacer, of the work arrays' size and 16 bytes more each time, moves them
        spacers.append(np.empty(partly_outside.size + 4 * size, np.float32))
        values.add(SampledFieldSimilarity(epsilon, nx, ny)(partly_outside))
    assert len(values) == 1


def test_a_field_pixel_counts_where_its_four_neighbours_were_sampled_inside():
    image = _texture((45, 55), 4)
    holes = np.random.default_rng(7).random(image.shape) < 0.05  # scattered pixels sampled outside
    samples = np.where(holes, np.float32(-1.0e4), image)
    nx, ny = normalized_gradient_field(image, gradient_epsilon(image))
    inside = ~holes
    expected = inside[1:-1, :-2] & inside[1:-1, 2:] & inside[:-2, 1:-1] & inside[2:, 1:-1]  # not the pixel itself
    _, count = sampled_tensor_similarity(samples, gradient_epsilon(image), nx, ny)
    assert count == np.count_nonzero(expected) < 43 * 53
