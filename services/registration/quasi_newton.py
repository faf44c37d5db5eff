"""Maximise a function of a few parameters from its value and gradient by BFGS steps inside a trust radius.

The MI and NMI refinement has the objective's analytic gradient
(:class:`services.registration.objective.ParzenObjective`), so each step costs one evaluation where a
finite-difference quadratic model (:mod:`services.registration.newton`) costs 1 + n (n + 3) / 2.
Parameters are scaled so that one unit moves the image corners by about one pixel, so one radius and one
tolerance fit every parameter. Hand-written for the reason given in :mod:`services.registration.newton`:
scipy.optimize's import alone costs more than the registration may.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def maximize_with_gradient(
    function: Callable[[np.ndarray], tuple[float, np.ndarray]],
    count: int,
    radius: float = 1.0,
    tolerance: float = 0.02,
    relative_gain: float = 1e-6,
    max_iterations: int = 30,
) -> tuple[np.ndarray, float]:
    """Maximise ``function`` of ``count`` parameters from the origin.

    Parameters
    ----------
    function : callable
        Maps a (count,) array to its value and gradient; a value of -inf or nan marks an invalid point.
    count : int
        Number of parameters.
    radius : float
        Longest step.
    tolerance : float
        The iteration stops when an accepted step is shorter than this...
    relative_gain : float
        ...or raises the value by less than this fraction of it.
    max_iterations : int
        Largest number of steps tried.

    Returns
    -------
    parameters : (count,) array
    value : float
        ``function(parameters)[0]``, never below ``function(0)[0]``.

    Notes
    -----
    Quasi-Newton ascent: the step s = B g, with g the gradient and B the BFGS approximation of the inverse
    of minus the Hessian, cut to ``radius``; B starts as the identity scaled by s.y / y.y after the first
    step (y the fall of the gradient along it) and is updated by
    B <- (I - rho s y^T) B (I - rho y s^T) + rho s s^T, rho = 1 / y.s, when y.s > 0. A step that does not
    raise the value is quartered up to twice; if none does, B is dropped and the next step is a gradient
    step as long as the last trial, and if a gradient step fails too the iteration stops.

    References
    ----------
    .. [1] J. Nocedal, S. J. Wright, "Numerical Optimization", 2nd ed., Springer 2006, chapter 6
       (equations 6.17 and 6.20).
    """
    if count < 1 or not radius > 0.0 or not tolerance > 0.0 or max_iterations < 1:
        raise ValueError("maximize_with_gradient needs at least one parameter, a positive radius and tolerance, "
                         "and at least one iteration.")

    def evaluate(point: np.ndarray) -> tuple[float, np.ndarray]:
        value, gradient = function(point)
        value = float(value)
        return (value, np.asarray(gradient, dtype=np.float64)) if np.isfinite(value) else (-np.inf, np.zeros(count))

    parameters = np.zeros(count)
    value, gradient = evaluate(parameters)
    if not np.isfinite(value):
        return parameters, value
    inverse = None  # the BFGS matrix B, unknown until the first step
    scale = radius  # length of a gradient step while B is unknown
    for _ in range(max_iterations):
        norm = float(np.linalg.norm(gradient))
        if norm == 0.0:
            break
        move = gradient * (scale / norm) if inverse is None else inverse @ gradient
        length = float(np.linalg.norm(move))
        if length > radius:
            move *= radius / length
        for _ in range(3):
            trial, trial_gradient = evaluate(parameters + move)
            if trial > value:
                break
            move = 0.25 * move
        if not trial > value:
            if inverse is None:
                break  # not even a short gradient step climbs: a maximum at this scale
            inverse, scale = None, float(np.linalg.norm(move))  # drop B; a gradient step as long as the last trial
            continue
        fall = gradient - trial_gradient  # y, the gradient of minus the function rising along the step
        curvature = float(move @ fall)
        if curvature > 0.0:
            if inverse is None:
                inverse = (curvature / float(fall @ fall)) * np.eye(count)
            rho = 1.0 / curvature
            left = np.eye(count) - rho * np.outer(move, fall)
            inverse = left @ inverse @ left.T + rho * np.outer(move, move)
        gain = trial - value
        parameters, value, gradient = parameters + move, trial, trial_gradient
        if float(np.linalg.norm(move)) < tolerance or gain < relative_gain * abs(value):
            break
    return parameters, value
