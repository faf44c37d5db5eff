import cv2
import numpy as np
import pytest

from services.geometry.distortion import opencv_distortion_terms, reprojection_errors

K = np.array([[900.0, 0, 330], [0, 910.0, 250], [0, 0, 1]])


@pytest.mark.parametrize("dist", [
    np.zeros(0), np.array([-0.2, 0.05, 0.001, -0.002]), np.array([-0.2, 0.05, 0.001, -0.002, 0.01]),
    np.array([0.1, -0.05, 0.001, 0.002, 0.01, 0.02, -0.01, 0.005]),
    np.array([0.1, -0.05, 0.001, 0.002, 0.01, 0.02, -0.01, 0.005, 0.001, -0.002, 0.0015, 0.0005, 0.02, -0.015]),
], ids=["none", "four", "five", "eight", "fourteen"])
def test_matches_opencv_projection(dist):
    rng = np.random.default_rng(0)
    normalized = rng.uniform(-0.5, 0.5, size=(500, 2))
    pixels, _ = cv2.projectPoints(np.column_stack([normalized, np.ones(500)]), np.zeros(3), np.zeros(3), K,
                                  dist if dist.size else None)
    assert reprojection_errors(normalized, pixels.reshape(-1, 2), K, dist).max() < 1e-9
    assert reprojection_errors(normalized, pixels.reshape(-1, 2) + [0.5, 0], K, dist).min() == pytest.approx(0.5)


def test_terms_are_padded_and_tilt_is_identity_without_tau():
    terms, tilt = opencv_distortion_terms(np.array([0.1, 0.2, 0.0, 0.0]))
    np.testing.assert_array_equal(terms, [0.1, 0.2] + [0.0] * 10)
    np.testing.assert_allclose(tilt, np.eye(3))
