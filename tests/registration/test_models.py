import numpy as np
import pytest

from services.registration.models import (
    MODELS,
    PARAMETER_COUNTS,
    apply_homography,
    corner_error,
    image_corners,
    similarity_about_centres,
    update_matrix,
)


@pytest.mark.parametrize("model", MODELS)
def test_zero_parameters_give_the_identity(model):
    np.testing.assert_allclose(update_matrix(model, np.zeros(PARAMETER_COUNTS[model]), 320, 256), np.eye(3), atol=1e-9)


@pytest.mark.parametrize("model", MODELS)
def test_a_unit_parameter_moves_the_corners_by_about_one_pixel(model):
    for index in range(PARAMETER_COUNTS[model]):
        parameters = np.zeros(PARAMETER_COUNTS[model])
        parameters[index] = 1.0
        motion = corner_error(np.eye(3), update_matrix(model, parameters, 320, 256), 320, 256)
        assert 0.2 < motion <= 1.01


def test_rigid_and_similarity_rotate_and_scale_about_the_image_centre():
    width, height = 320, 256
    centre = np.array([[(width - 1) / 2, (height - 1) / 2]])
    radius = 0.5 * np.hypot(width, height)
    similarity = update_matrix("similarity", [0.0, 0.0, 0.1 * radius, np.log(1.2) * radius], width, height)
    np.testing.assert_allclose(apply_homography(similarity, centre), centre)
    linear = similarity[:2, :2]
    np.testing.assert_allclose(linear, 1.2 * np.array([[np.cos(0.1), -np.sin(0.1)], [np.sin(0.1), np.cos(0.1)]]))
    rigid = update_matrix("rigid", [3.0, -2.0, 0.1 * radius], width, height)
    np.testing.assert_allclose(np.linalg.det(rigid[:2, :2]), 1.0)
    np.testing.assert_allclose(apply_homography(rigid, centre), centre + [3.0, -2.0])


def test_homography_parameters_are_the_corner_displacements():
    displacement = np.array([1.0, 2.0, -3.0, 0.5, 2.5, -1.0, 0.0, 4.0])
    matrix = update_matrix("homography", displacement, 320, 256)
    corners = image_corners(320, 256)
    np.testing.assert_allclose(apply_homography(matrix, corners), corners + displacement.reshape(4, 2), atol=1e-4)


def test_similarity_about_centres_maps_centre_to_shifted_centre():
    matrix = similarity_about_centres(np.array([10.0, 20.0]), np.array([100.0, 50.0]), 2.0, 0.3, np.array([5.0, -4.0]))
    np.testing.assert_allclose(apply_homography(matrix, np.array([[10.0, 20.0]])), [[105.0, 46.0]])


def test_corner_error_of_a_pure_shift_is_its_length():
    shifted = np.array([[1.0, 0.0, 3.0], [0.0, 1.0, 4.0], [0.0, 0.0, 1.0]])
    assert corner_error(np.eye(3), shifted, 320, 256) == pytest.approx(5.0)
    assert corner_error(shifted, shifted, 320, 256) == 0.0


def test_bad_model_or_parameter_count_is_refused():
    with pytest.raises(ValueError, match="Unknown registration model"):
        update_matrix("elastic", [0.0], 10, 10)
    with pytest.raises(ValueError, match="4 parameters"):
        update_matrix("similarity", [0.0, 0.0], 10, 10)
