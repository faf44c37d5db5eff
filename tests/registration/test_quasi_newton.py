import numpy as np
import pytest

from services.registration.quasi_newton import maximize_with_gradient


def test_a_concave_quadratic_is_maximised_in_a_few_gradient_evaluations():
    peak = np.array([0.7, -0.4, 0.3, 0.2])
    curvature = np.array([[2.0, 0.5, 0.0, 0.1], [0.5, 1.0, 0.2, 0.0], [0.0, 0.2, 3.0, 0.3], [0.1, 0.0, 0.3, 1.5]])
    calls = []

    def function(p):
        calls.append(p)
        return 5.0 - 0.5 * (p - peak) @ curvature @ (p - peak), -curvature @ (p - peak)

    parameters, value = maximize_with_gradient(function, 4, radius=2.0, tolerance=1e-6, relative_gain=0.0)
    np.testing.assert_allclose(parameters, peak, atol=1e-5)
    assert value == pytest.approx(5.0)
    assert len(calls) <= 25  # a finite-difference Newton model of 4 parameters alone costs 15 evaluations


def test_a_peak_beyond_the_radius_is_reached_in_several_steps():
    peak = np.array([6.0, -3.0])

    def function(p):  # not quadratic: a Gaussian, convex far from its peak
        value = float(np.exp(-0.02 * np.sum((p - peak) ** 2)))
        return value, -0.04 * (p - peak) * value

    parameters, value = maximize_with_gradient(function, 2, radius=1.0, tolerance=1e-4, relative_gain=0.0,
                                               max_iterations=60)
    np.testing.assert_allclose(parameters, peak, atol=0.01)


def test_invalid_points_are_avoided_and_the_start_is_never_made_worse():
    def function(p):  # the peak lies beyond a wall of invalid points
        if p[0] > 0.3:
            return -np.inf, np.zeros(2)
        return float(-np.sum((p - np.array([2.0, 0.0])) ** 2)), -2.0 * (p - np.array([2.0, 0.0]))

    parameters, value = maximize_with_gradient(function, 2, radius=0.5, tolerance=1e-3)
    assert parameters[0] <= 0.3 and value >= function(np.zeros(2))[0]
    assert parameters[0] > 0.2  # it went most of the way to the wall


def test_bad_settings_are_refused_with_a_sentence():
    with pytest.raises(ValueError, match="positive radius"):
        maximize_with_gradient(lambda p: (0.0, np.zeros(2)), 2, radius=0.0)
    with pytest.raises(ValueError, match="at least one parameter"):
        maximize_with_gradient(lambda p: (0.0, np.zeros(0)), 0)
