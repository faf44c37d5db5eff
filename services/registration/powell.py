"""Powell's derivative-free minimisation, as scipy.optimize.minimize(method="Powell") without bounds.

Written out here because importing scipy.optimize costs about 0.6 s, more than the whole registration
of a 500x300 pair, at the start of every `thermofield register` process. The algorithm, its constants and
its stopping rules are scipy's (1.x ``_minimize_powell``, ``_linesearch_powell``, ``bracket`` and
``Brent``), so it visits the same points; the one difference is that each line search reuses the
objective value at its start instead of evaluating it again.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

_GOLD = 1.618034  # bracket expansion: the golden ratio
_GROW_LIMIT = 110.0  # largest parabolic step of the bracket, in units of its last interval
_CG = 0.3819660  # Brent's golden-section fraction, (3 - sqrt(5)) / 2
_MIN_TOL = 1.0e-11  # Brent's absolute tolerance floor
_BRENT_ITERATIONS = 500
_BRACKET_ITERATIONS = 1000
_VERY_SMALL = 1e-21


def _bracket(f: Callable[[float], float], f0: float) -> tuple[float, float, float, float, float, float]:
    """Three points a, b, c with f(b) below f(a) and f(c), expanding downhill from 0 and 1 (scipy's ``bracket``).

    Returns the best of the points found instead when no valid bracket exists (scipy's recovery).
    """
    xa, xb = 0.0, 1.0
    fa, fb = f0, f(xb)
    if fa < fb:
        xa, xb, fa, fb = xb, xa, fb, fa
    xc = xb + _GOLD * (xb - xa)
    fc = f(xc)
    iterations = 0
    while fc < fb:
        tmp1 = (xb - xa) * (fb - fc)
        tmp2 = (xb - xc) * (fb - fa)
        value = tmp2 - tmp1
        denominator = 2.0 * _VERY_SMALL if abs(value) < _VERY_SMALL else 2.0 * value
        w = xb - ((xb - xc) * tmp2 - (xb - xa) * tmp1) / denominator
        w_limit = xb + _GROW_LIMIT * (xc - xb)
        if iterations > _BRACKET_ITERATIONS:
            break
        iterations += 1
        if (w - xc) * (xb - w) > 0.0:
            fw = f(w)
            if fw < fc:
                xa, xb, fa, fb = xb, w, fb, fw
                break
            if fw > fb:
                xc, fc = w, fw
                break
            w = xc + _GOLD * (xc - xb)
            fw = f(w)
        elif (w - w_limit) * (w_limit - xc) >= 0.0:
            w = w_limit
            fw = f(w)
        elif (w - w_limit) * (xc - w) > 0.0:
            fw = f(w)
            if fw < fc:
                xb, xc = xc, w
                w = xc + _GOLD * (xc - xb)
                fb, fc = fc, fw
                fw = f(w)
        else:
            w = xc + _GOLD * (xc - xb)
            fw = f(w)
        xa, xb, xc = xb, xc, w
        fa, fb, fc = fb, fc, fw
    valid = ((fb < fc and fb <= fa) or (fb < fa and fb <= fc)) and (xa < xb < xc or xc < xb < xa) and (
        np.isfinite(xa) and np.isfinite(xb) and np.isfinite(xc))
    return xa, xb, xc, fa, fb, fc, valid


def _brent(f: Callable[[float], float], f0: float, tol: float) -> tuple[float, float]:
    """Minimise f along a line from 0 by bracketing and Brent's parabolic/golden-section search."""
    xa, xb, xc, fa, fb, fc, valid = _bracket(f, f0)
    if not valid:
        if np.isnan([xa, xb, xc, fa, fb, fc]).any():
            return np.nan, np.nan
        best = int(np.argmin([fa, fb, fc]))
        return (xa, xb, xc)[best], (fa, fb, fc)[best]
    x = w = v = xb
    fw = fv = fx = fb
    a, b = (xa, xc) if xa < xc else (xc, xa)
    deltax = 0.0
    rat = 0.0
    for _ in range(_BRENT_ITERATIONS):
        tol1 = tol * abs(x) + _MIN_TOL
        tol2 = 2.0 * tol1
        xmid = 0.5 * (a + b)
        if abs(x - xmid) < (tol2 - 0.5 * (b - a)):
            break
        if abs(deltax) <= tol1:
            deltax = a - x if x >= xmid else b - x
            rat = _CG * deltax
        else:
            tmp1 = (x - w) * (fx - fv)
            tmp2 = (x - v) * (fx - fw)
            p = (x - v) * tmp2 - (x - w) * tmp1
            tmp2 = 2.0 * (tmp2 - tmp1)
            if tmp2 > 0.0:
                p = -p
            tmp2 = abs(tmp2)
            previous = deltax
            deltax = rat
            if p > tmp2 * (a - x) and p < tmp2 * (b - x) and abs(p) < abs(0.5 * tmp2 * previous):
                rat = p * 1.0 / tmp2
                u = x + rat
                if (u - a) < tol2 or (b - u) < tol2:
                    rat = tol1 if xmid - x >= 0 else -tol1
            else:
                deltax = a - x if x >= xmid else b - x
                rat = _CG * deltax
        u = (x + tol1 if rat >= 0 else x - tol1) if abs(rat) < tol1 else x + rat
        fu = f(u)
        if fu > fx:
            if u < x:
                a = u
            else:
                b = u
            if fu <= fw or w == x:
                v, w, fv, fw = w, u, fw, fu
            elif fu <= fv or v == x or v == w:
                v, fv = u, fu
        else:
            if u >= x:
                a = x
            else:
                b = x
            v, w, x = w, x, u
            fv, fw, fx = fw, fx, fu
    return x, fx


def _line_search(
    f: Callable[[np.ndarray], float], point: np.ndarray, direction: np.ndarray, value: float, tol: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """The minimum of f(point + alpha direction): its value, the new point and the step taken."""
    if not np.any(direction):
        return value, point, direction
    alpha, found = _brent(lambda step: f(point + step * direction), value, tol)
    step = alpha * direction
    return found, point + step, step


def minimize_powell(
    f: Callable[[np.ndarray], float], start: np.ndarray, directions: np.ndarray, xtol: float, ftol: float
) -> tuple[np.ndarray, float]:
    """Minimise ``f`` from ``start`` by Powell's conjugate-direction method; return the point and its value.

    Parameters
    ----------
    f : callable
        Objective of a 1-D parameter array.
    start : (n,) array
        First point.
    directions : (n, n) array
        First search directions (rows); their lengths set the first steps.
    xtol : float
        Line-search tolerance, relative, as scipy's ``xtol`` (each line search stops at 100 ``xtol``).
    ftol : float
        Stop when an iteration lowers f by less than this fraction.

    Notes
    -----
    Each iteration minimises f along every direction in turn (bracketing, then Brent's method), then
    replaces the direction of largest decrease by the iteration's overall step when Powell's test says
    the new direction helps. At most 1000 n evaluations.

    References
    ----------
    .. [1] M. J. D. Powell, "An efficient method for finding the minimum of a function of several variables
       without calculating derivatives", The Computer Journal 7(2), 1964.
    .. [2] W. H. Press et al., Numerical Recipes, 3rd ed., section 10.7 (the modified algorithm scipy follows).
    """
    count = len(start)
    budget = 1000 * count
    evaluations = 0

    def counted(parameters: np.ndarray) -> float:
        nonlocal evaluations
        evaluations += 1
        return f(parameters)

    directions = np.array(directions, dtype=float)
    x = np.asarray(start, dtype=float).ravel().copy()
    value = counted(x)
    previous_x = x.copy()
    for _ in range(budget):
        start_value = value
        biggest, decrease = 0, 0.0
        for index in range(count):
            before = value
            value, x, _ = _line_search(counted, x, directions[index], value, xtol * 100)
            if before - value > decrease:
                decrease, biggest = before - value, index
        if 2.0 * (start_value - value) <= ftol * (abs(start_value) + abs(value)) + 1e-20:
            break
        if evaluations >= budget or (np.isnan(start_value) and np.isnan(value)):
            break
        step = x - previous_x
        previous_x = x.copy()
        extrapolated = counted(x + step)
        if start_value > extrapolated:
            t = 2.0 * (start_value + extrapolated - 2.0 * value) * (start_value - value - decrease) ** 2
            t -= decrease * (start_value - extrapolated) ** 2
            if t < 0.0:
                value, x, step = _line_search(counted, x, step, value, xtol * 100)
                if np.any(step):
                    directions[biggest] = directions[-1]
                    directions[-1] = step
    return x, value
