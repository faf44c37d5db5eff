import numpy as np
import pytest

from services.registration.newton import maximize


def test_a_concave_quadratic_is_maximised_by_newton_steps():
    peak = np.array([0.7, -0.4, 0.3])
    curvature = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 3.0]])
    calls = []

    def function(p):
        calls.append(p)
        return 5.0 - 0.5 * (p - peak) @ curvature @ (p - peak)

    parameters, value = maximize(function, 3, step=0.5, tolerance=1e-6, max_iterations=3)
    np.testing.assert_allclose(parameters, peak, atol=1e-4)  # the damping's 1e-3 margin shortens each step a little
    assert value == pytest.approx(5.0)
    assert len(calls) <= 3 * (1 + 3 + 3 + 3 + 3)  # a 10-point model and up to 3 trials per iteration


def test_a_peak_beyond_the_trust_radius_is_reached_in_several_steps():
    peak = np.array([6.0, -3.0])

    def function(p):  # not quadratic: a Gaussian, convex far from its peak
        return float(np.exp(-0.02 * np.sum((p - peak) ** 2)))

    parameters, value = maximize(function, 2, step=1.0, min_step=0.125, tolerance=1e-3, max_iterations=30)
    np.testing.assert_allclose(parameters, peak, atol=0.02)
    assert value > function(np.zeros(2))


def test_invalid_points_are_avoided_and_the_start_is_never_made_worse():
    def function(p):  # the peak lies beyond a wall of invalid points
        return -np.inf if p[0] > 0.3 else float(-np.sum((p - np.array([2.0, 0.0])) ** 2))

    parameters, value = maximize(function, 2, step=0.5, min_step=0.125, max_iterations=20)
    assert parameters[0] <= 0.3 and value >= function(np.zeros(2))
    assert parameters[0] > 0.1  # it went as far towards the peak as the wall allows, within a stencil


def test_bad_settings_are_refused_with_a_sentence():
    with pytest.raises(ValueError, match="min_step <= step"):
        maximize(lambda p: 0.0, 2, step=0.5, min_step=1.0)
    with pytest.raises(ValueError, match="at least one parameter"):
        maximize(lambda p: 0.0, 0)


def test_a_model_that_predicted_well_lends_its_curvature_and_the_peak_is_still_reached(monkeypatch):
    from services.registration import newton

    peak = np.array([5.0, -4.0, 3.0, 2.0])
    curvature = np.array([[2.0, 0.8, 0.0, 0.3], [0.8, 1.5, 0.4, 0.0], [0.0, 0.4, 1.0, 0.2], [0.3, 0.0, 0.2, 1.2]])
    models = []
    measure = newton._quadratic_model

    def recorded(function, centre, value, step, kept=None):
        models.append(kept is not None)
        return measure(function, centre, value, step, kept)

    monkeypatch.setattr(newton, "_quadratic_model", recorded)
    parameters, _ = maximize(lambda p: -0.5 * (p - peak) @ curvature @ (p - peak), 4, step=0.5, tolerance=1e-6,
                             max_iterations=30)
    np.testing.assert_allclose(parameters, peak, atol=1e-3)
    assert models[0] is False and any(models)  # the first model measures its mixed terms; later ones reuse them


def test_a_batch_evaluator_changes_neither_the_path_nor_the_result():
    peak = np.array([1.5, -0.7, 0.4, 2.0])
    curvature = np.diag([2.0, 1.0, 0.5, 1.5]) + 0.2

    def function(point):
        return float(-0.5 * (point - peak) @ curvature @ (point - peak) + 0.01 * np.sin(40.0 * point).sum())

    batches = []

    def evaluate_many(points):
        batches.append(len(points))
        return [function(point) for point in reversed(points)][::-1]

    alone = maximize(function, 4, step=0.5, min_step=0.125, tolerance=1e-4, max_iterations=30)
    batched = maximize(function, 4, step=0.5, min_step=0.125, tolerance=1e-4, max_iterations=30,
                       evaluate_many=evaluate_many)
    assert np.array_equal(alone[0], batched[0]) and alone[1] == batched[1]
    assert batches[0] == 8 and 6 in batches  # the axis points, then the mixed points, as batches


def test_the_climb_stops_where_the_caller_says_and_costs_fewer_evaluations():
    peak = np.array([3.0, -2.0])
    calls = {"free": 0, "stopped": 0}

    def counted(name):
        def function(p):
            calls[name] += 1
            return float(np.exp(-0.05 * np.sum((p - peak) ** 2)))
        return function

    free, _ = maximize(counted("free"), 2, step=1.0, min_step=0.25, tolerance=1e-3, max_iterations=30)
    stopped, value = maximize(counted("stopped"), 2, step=1.0, min_step=0.25, tolerance=1e-3, max_iterations=30,
                              stop=lambda p: np.linalg.norm(p - free) <= 0.5)
    assert np.linalg.norm(stopped - free) <= 0.5 < np.linalg.norm(free)  # it stopped on arriving, not at the start
    assert value == pytest.approx(np.exp(-0.05 * np.sum((stopped - peak) ** 2)))
    assert calls["stopped"] < calls["free"]


def test_a_start_that_already_satisfies_the_stop_is_not_climbed():
    calls = []
    parameters, value = maximize(lambda p: calls.append(p) or -float(p @ p), 2, stop=lambda p: True)
    assert np.array_equal(parameters, np.zeros(2)) and value == 0.0 and len(calls) == 1


def test_no_point_is_evaluated_twice():
    peak = np.array([2.3, -1.1, 0.6, 1.7])

    def function(point):  # rough on a small scale, as the registration's objectives: some stencils return
        return float(-np.abs(point - peak).sum() + 0.05 * np.cos(9.0 * point).sum())  # to points seen before

    for evaluate_many in (None, lambda points: [function(point) for point in points]):
        seen = []

        def recorded(point):
            seen.append(point.tobytes())
            return function(point)

        many = None if evaluate_many is None else (lambda points: [recorded(point) for point in points])
        parameters, value = maximize(recorded, 4, step=1.0, min_step=0.25, tolerance=1e-3, max_iterations=40,
                                     evaluate_many=many)
        assert len(seen) == len(set(seen)) > 20
        assert value == function(parameters) and np.abs(parameters - peak).sum() < 1.0
