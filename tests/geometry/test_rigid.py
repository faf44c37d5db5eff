"""Tests of services.geometry.rigid."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from services.geometry.rigid import rigid_transform


def test_rigid_transform_matches_the_matrix_product_and_inverts():
    rng = np.random.default_rng(3)
    points = rng.normal(0, 100, (1000, 3))
    rotation = Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix()
    translation = np.array([12.5, -40.0, 310.0])
    moved = rigid_transform(points, rotation, translation)
    np.testing.assert_allclose(moved, points @ rotation.T + translation, atol=1e-10)
    back = rigid_transform(moved, rotation.T, -rotation.T @ translation)
    np.testing.assert_allclose(back, points, atol=1e-10)


def test_rigid_transform_takes_non_contiguous_and_empty_arrays():
    points = np.arange(30.0).reshape(10, 3)[::2]
    np.testing.assert_allclose(rigid_transform(points, np.eye(3), np.ones(3)), points + 1)
    assert rigid_transform(np.zeros((0, 3)), np.eye(3), np.zeros(3)).shape == (0, 3)


def test_rigid_transform_rejects_points_that_are_not_n_by_3():
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        rigid_transform(np.zeros((4, 2)), np.eye(3), np.zeros(3))
