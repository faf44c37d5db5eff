"""Maximise a function of a few parameters by damped Newton steps on a finite-difference quadratic model.

The registration refines 2 to 8 transform parameters, scaled so that one unit
moves the image corners by about one pixel, on an objective (MI, NMI, NGF)
that is rough at the scale of a hundredth of a pixel but smooth at the scale
of half a pixel. A quadratic model fitted on a stencil of that half-pixel
size sees the smooth shape and ignores the roughness, and a few Newton steps
on it converge: 14 evaluations for the first model of 4 parameters, 8 for
each next one, which keeps the last model's curvature while its steps succeed.

Hand-written because the library optimisers do not fit the command's budget:
importing scipy.optimize alone takes longer (about 0.5 s) than the whole
registration is allowed to, and OpenCV has no general-purpose optimiser.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def _quadratic_model(
    evaluate: Callable[[list[np.ndarray]], list[float]], centre: np.ndarray, value: float, step: float,
    kept: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Gradient and Hessian by finite differences at ``centre``, and the best stencil point.

    Central differences on the axes, one forward point per pair of axes for the mixed derivatives:
    1 + n (n + 3) / 2 points, of which the centre's ``value`` is given. With a ``kept`` Hessian, its mixed
    derivatives are reused and only the 2 n axis points are evaluated. ``evaluate`` maps a list of points
    to their values (-inf where invalid).
    """
    count = centre.size
    basis = np.eye(count)
    offsets = [(axis, sign) for axis in range(count) for sign in (1.0, -1.0)]
    points = [centre + sign * step * basis[axis] for axis, sign in offsets]
    values = np.asarray(evaluate(points), dtype=float)
    plus, minus = values[0::2], values[1::2]
    if kept is None:
        pairs = [(first, second) for first in range(count) for second in range(first + 1, count)]
        mixed_points = [centre + step * (basis[first] + basis[second]) for first, second in pairs]
        mixed = np.asarray(evaluate(mixed_points), dtype=float)
        points, values = points + mixed_points, np.concatenate([values, mixed])
    best_point, best_value = centre, value
    for point, point_value in zip(points, values):  # the first of equal values, in the stencil's order
        if point_value > best_value:
            best_point, best_value = point, float(point_value)
    with np.errstate(invalid="ignore"):  # an invalid (-inf) stencil point makes the model nan, checked by the caller
        gradient = (plus - minus) / (2.0 * step)
        hessian = np.diag((plus - 2.0 * value + minus) / step**2)
        if kept is not None:
            return gradient, hessian + kept - np.diag(np.diag(kept)), best_point, best_value
        for (first, second), both in zip(pairs, mixed):
            hessian[first, second] = hessian[second, first] = (both - plus[first] - plus[second] + value) / step**2
    return gradient, hessian, best_point, best_value


def _ascent_step(gradient: np.ndarray, hessian: np.ndarray, radius: float) -> np.ndarray:
    """The Newton step of the model, damped until the model curves down in every direction, at most ``radius`` long."""
    damping = max(0.0, float(np.linalg.eigvalsh(hessian).max()))
    curvature = hessian - (damping + 1e-9 + 1e-3 * float(np.abs(hessian).max())) * np.eye(gradient.size)
    step = np.linalg.solve(curvature, -gradient)
    length = float(np.linalg.norm(step))
    return step * (radius / length) if length > radius else step


def maximize(
    function: Callable[[np.ndarray], float],
    count: int,
    step: float = 1.0,
    min_step: float | None = None,
    tolerance: float = 0.02,
    relative_gain: float = 1e-5,
    max_iterations: int = 20,
    evaluate_many: Callable[[list[np.ndarray]], list[float]] | None = None,
    stop: Callable[[np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, float]:
    """Maximise ``function`` of ``count`` parameters from the origin.

    Parameters
    ----------
    function : callable
        Maps a (count,) array to a float; -inf or nan marks an invalid point.
    count : int
        Number of parameters.
    step : float
        First stencil size of the finite differences, and half the first trust radius.
    min_step : float, optional
        Smallest stencil size (default ``step``): the stencil is halved down to it when the iteration
        converges or stalls at the current size.
    tolerance : float
        The iteration converges when an accepted step is shorter than this...
    relative_gain : float
        ...or raises ``function`` by less than this fraction of its value.
    max_iterations : int
        Largest number of model fits.
    evaluate_many : callable, optional
        Maps a list of points to their ``function`` values, in order (by default one after the other):
        a stencil's points are independent, so a caller may spread them over threads. The result does
        not depend on it.
    stop : callable, optional
        Called with the start and with every point the iteration moves to; when it returns true the
        iteration ends there at once (a caller that knows where this start leads, e.g. a maximum that
        another start already reached, need not climb it again).

    Returns
    -------
    parameters : (count,) array
    value : float
        ``function(parameters)``, never below ``function(0)``.

    Notes
    -----
    Each iteration fits the quadratic model m(s) = f + g.s + s.H s / 2 by
    finite differences of size ``step`` and moves by the Newton step
    s = -(H - mu I)^-1 g, with mu >= 0 the damping that makes H - mu I
    negative definite (Levenberg-Marquardt style), cut to the trust radius.
    A model whose full step increased f lends its mixed derivatives to the
    next model at the same stencil, which then measures only the gradient and
    the diagonal (2 n points instead of n (n + 3) / 2): where the iteration
    stops, the central-difference gradient vanishes either way, so this
    changes the path, not the point the path converges to (a quasi-Newton
    saving, cf. [1], chapter 6).
    A step that does not increase f is quartered up to twice; if none does,
    the best stencil point, if better, is taken instead, and if no stencil
    point is better either the stencil is halved (down to ``min_step``); so
    is it when the iteration converges at the current stencil, so that the
    last model is the most local one.
    The trust radius follows the accepted steps (twice the last one, at
    least the stencil).
    No point is evaluated twice: a stencil centred on a stencil point just
    taken, or a trial step that lands on a point measured before, reuses
    its value (on the TNO pairs 3 % to 5 % of a registration's evaluations).

    References
    ----------
    .. [1] J. Nocedal, S. J. Wright, "Numerical Optimization", 2nd ed.,
       Springer 2006, chapters 4 (trust regions), 6 (quasi-Newton methods) and 8 (finite differences).
    """
    min_step = step if min_step is None else min_step
    if count < 1 or not 0.0 < min_step <= step or not tolerance > 0.0 or max_iterations < 1:
        raise ValueError("maximize needs at least one parameter, 0 < min_step <= step, a positive tolerance "
                         "and at least one iteration.")

    known: dict[bytes, float] = {}  # the values of the points evaluated so far, by the exact point

    def finite(point: np.ndarray) -> float:
        key = point.tobytes()
        if key not in known:
            value = float(function(point))
            known[key] = value if np.isfinite(value) else -np.inf
        return known[key]

    def finite_many(points: list[np.ndarray]) -> list[float]:
        if evaluate_many is None:
            return [finite(point) for point in points]
        new = list({point.tobytes(): point for point in points if point.tobytes() not in known}.items())
        if new:
            values = evaluate_many([point for _, point in new])
            known.update((key, float(value) if np.isfinite(value) else -np.inf) for (key, _), value in zip(new, values))
        return [known[point.tobytes()] for point in points]

    parameters = np.zeros(count)
    value = finite(parameters)
    if stop is not None and stop(parameters):
        return parameters, value
    radius = 2.0 * step
    kept = None  # the Hessian whose mixed derivatives the next model reuses
    for _ in range(max_iterations):
        gradient, hessian, stencil_point, stencil_value = _quadratic_model(finite_many, parameters, value, step, kept)
        kept, trial = None, -np.inf
        if np.all(np.isfinite(gradient)) and np.all(np.isfinite(hessian)):
            move = _ascent_step(gradient, hessian, radius)
            for attempt in range(3):
                trial = finite(parameters + move)
                if trial > value:
                    if attempt == 0 and count > 1:  # the model predicted well: keep its curvature
                        kept = hessian
                    break
                move = 0.25 * move
        if trial > value and trial >= stencil_value:
            gain = trial - value
            parameters, value = parameters + move, trial
            if stop is not None and stop(parameters):
                break
            length = float(np.linalg.norm(move))
            radius = max(step, 4.0 * length)
            if length < tolerance or gain < relative_gain * abs(value):
                if step <= min_step:
                    break
                step, radius, kept = 0.5 * step, step, None  # converged at this scale: refine with a smaller model
        elif stencil_value > value:
            parameters, value, kept = stencil_point, stencil_value, None
            if stop is not None and stop(parameters):
                break
        elif step > min_step:  # no better point at this scale: fit a smaller model
            step, radius = 0.5 * step, step
        else:
            break
    return parameters, value
