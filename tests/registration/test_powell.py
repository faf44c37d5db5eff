"""The hand-written Powell minimiser against scipy.optimize's, which it transcribes."""

import numpy as np
import pytest
from scipy.optimize import minimize, rosen

from services.registration.powell import minimize_powell


@pytest.mark.parametrize("start", [np.array([-1.2, 1.0]), np.array([0.5, -0.3, 2.0, 1.1])])
def test_powell_visits_scipys_minimum(start):
    directions = 0.5 * np.eye(start.size)
    expected = minimize(rosen, start, method="Powell", options={"xtol": 0.02, "ftol": 1e-5, "direc": directions.copy()})
    point, value = minimize_powell(rosen, start, directions, 0.02, 1e-5)
    np.testing.assert_array_equal(point, expected.x)
    assert value == expected.fun


def test_powell_finds_a_quadratic_minimum():
    centre = np.array([3.0, -2.0, 0.5])
    point, value = minimize_powell(lambda x: float(np.sum((x - centre) ** 2)), np.zeros(3), np.eye(3), 1e-4, 1e-10)
    np.testing.assert_allclose(point, centre, atol=1e-3)
    assert value < 1e-6
