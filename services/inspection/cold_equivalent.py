"""Cold-equivalent geometry: where each measured point of a hot part will be once the part is at 20 degC."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from services.fusion.radiometry import KELVIN_OFFSET
from services.inspection.materials import Material
from services.inspection.point_rows import column_mean, finite_rows

_TREND_SAMPLES = 20000
_MIN_SCALE_K = 0.01  # below any camera's NETD: an exactly uniform field keeps its weights
NEIGHBOURHOOD_MM = 25.0
"""Radius of the neighbourhood whose own temperatures stand in for a point without one."""
NEIGHBOURS = 8
NEIGHBOURHOOD_SAMPLES = 10000
"""Points with a temperature searched for neighbours, evenly drawn (about one per 4 mm^2 of a billet's view)."""


@dataclass(frozen=True)
class ColdGeometry:
    """The cold-equivalent points and what went into them.

    Attributes
    ----------
    points : (N, 3) array
        Cold-equivalent points, same frame as the input.
    temperature : (N,) array
        The temperature used at each point, degrees C (its own, or the fallback).
    fallback : (N,) bool array
        Points without a finite temperature of their own, given their neighbourhood's (or the trend's).
    strain : (N,) array
        Mean thermal strain along each point's segment from the centre.
    centre : (3,) array
        The fixed point of the expansion.
    trend : (4,) array
        The linear temperature trend T(X) = a + b . X (a, b_x, b_y, b_z) over the part.
    """

    points: np.ndarray
    temperature: np.ndarray
    fallback: np.ndarray
    strain: np.ndarray
    centre: np.ndarray
    trend: np.ndarray


def temperature_trend(points: np.ndarray, temperature: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Robust linear fit T(X) = a + b . X of temperatures over points; (a, b_x, b_y, b_z).

    Iteratively reweighted least squares with Tukey's biweight (c = 4.685 robust sigmas, the sigma
    from the median absolute deviation) on at most 20 000 evenly drawn points, so that hot and cold
    spots do not tilt the trend.
    """
    finite = np.isfinite(temperature) & finite_rows(points)
    index = np.flatnonzero(finite)
    if len(index) < 4:
        raise ValueError(f"Only {len(index)} points have a temperature; at least 4 are needed for the part's "
                         "temperature trend.")
    if len(index) > _TREND_SAMPLES:
        index = index[np.linspace(0, len(index) - 1, _TREND_SAMPLES).astype(np.intp)]
    design = np.column_stack([np.ones(len(index)), points[index]])
    values = temperature[index].astype(np.float64)
    weights = np.ones(len(index))
    coefficients = np.zeros(4)
    for _ in range(iterations):
        root = np.sqrt(weights)
        coefficients = np.linalg.lstsq(design * root[:, None], values * root, rcond=None)[0]
        residual = values - design @ coefficients
        sigma = max(1.4826 * np.median(np.abs(residual - np.median(residual))), _MIN_SCALE_K)
        u = residual / (4.685 * sigma)
        weights = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
    return coefficients


def neighbourhood_temperature(points: np.ndarray, temperature: np.ndarray, trend: np.ndarray, wanted: np.ndarray,
                              radius_mm: float = NEIGHBOURHOOD_MM, neighbours: int = NEIGHBOURS) -> np.ndarray:
    """Temperatures for the points ``wanted`` (indices) from the part's points around them that have their own.

    T(X) = T_lin(X) + median_j (T_j - T_lin(X_j)) over the ``neighbours`` nearest points with a finite
    temperature within ``radius_mm`` of X (at most 10 000 of them, evenly drawn, are searched): the trend
    carries the gradient across the gap, the neighbours' median departure from it the local hot or cold
    spot. Where no such point lies within the radius, the trend T_lin(X) alone.
    """
    wanted = np.asarray(wanted, dtype=np.intp)
    at = points[wanted] @ trend[1:] + trend[0]
    own = np.flatnonzero(np.isfinite(temperature) & finite_rows(points))
    if len(wanted) == 0 or len(own) == 0:
        return at
    if len(own) > NEIGHBOURHOOD_SAMPLES:
        own = own[np.linspace(0, len(own) - 1, NEIGHBOURHOOD_SAMPLES).astype(np.intp)]
    departure = temperature[own] - (points[own] @ trend[1:] + trend[0])
    tree = cKDTree(points[own])
    query = np.where(np.isfinite(points[wanted]), points[wanted], 0.0)
    distance, index = tree.query(query, k=min(neighbours, len(own)), distance_upper_bound=radius_mm)
    distance, index = distance.reshape(len(wanted), -1), index.reshape(len(wanted), -1)
    found = np.isfinite(distance)
    values = np.where(found, departure[np.minimum(index, len(own) - 1)], np.nan)
    some = found.any(axis=1)
    if some.any():
        at[some] += np.nanmedian(values[some], axis=1)
    return at


def cold_equivalent(points: np.ndarray, temperature: np.ndarray, material: Material,
                    centre: np.ndarray | None = None) -> ColdGeometry:
    """Move hot points to where they will be when the part has cooled to 20 degC.

    Parameters
    ----------
    points : (N, 3) array
        Measured (hot) points of one part, mm.
    temperature : (N,) array
        Each point's measured temperature, degrees C; NaN where none was measured.
    material : Material
        The thermal-elongation table.
    centre : (3,) array, optional
        The point that stays fixed (the part's centre); default the points' centroid.

    Returns
    -------
    ColdGeometry
        Cold points, the temperatures used and the fallback flags.

    Notes
    -----
    The part is taken to expand freely (no stress) with the isotropic thermal strain
    eps(T) = Delta l / l of its material. Along the straight segment from the centre c to a hot
    point X the hot length is the integral of (1 + eps) over the cold length, so

        X_cold = c + (X - c) / (1 + eps_bar),   eps_bar = int_0^1 eps(T(c + s (X - c))) ds.

    The interior temperature along the segment is not measured: it is modelled as the part's linear
    surface trend T_lin(X) = a + b . X (robust fit to all points) plus the point's own departure from
    the trend, growing linearly from the centre, T(s) = T_lin(c + s (X - c)) + s (T(X) - T_lin(X)).
    That is T(s) = T_lin(c) + s (T(X) - T_lin(c)), linear in s, so eps_bar is the mean strain over
    [T_lin(c), T(X)], which the piecewise-linear table integrates exactly (``Material.mean_strain``).
    For a uniform temperature this is the exact uniform scaling; for a linear field it is exact to
    second order in the strain; a hot or cold spot acts on its own points. Points without a
    temperature (unseen by the thermal camera, or mixed edge pixels the fusion left NaN) take the
    trend at their position plus the median departure from it of their part's points within 25 mm
    that have their own (``neighbourhood_temperature``), the trend alone where none is (flagged). Thermal stresses, plastic flow and a core hotter than the surface are not modelled.
    Strains are the material table's, from 20 degC (EN 1993-1-2 [1]_ for steel).

    References
    ----------
    .. [1] EN 1993-1-2:2005, Eurocode 3: Design of steel structures, Part 1-2: Structural fire
       design, section 3.4.1.1 and annex C.
    """
    points = np.asarray(points, dtype=np.float64)
    temperature = np.asarray(temperature, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or temperature.shape != (len(points),):
        raise ValueError(f"points must have shape (N, 3) and temperature (N,); got {points.shape} and "
                         f"{temperature.shape}.")
    trend = temperature_trend(points, temperature)
    centre = column_mean(points) if centre is None else np.asarray(centre, dtype=np.float64)
    fallback = ~np.isfinite(temperature)
    used = temperature.copy()
    used[fallback] = neighbourhood_temperature(points, temperature, trend, np.flatnonzero(fallback))
    if fallback.any() and not np.all(used[fallback] > -KELVIN_OFFSET):
        raise ValueError(f"The part's temperature trend, fitted to its {int((~fallback).sum())} points with a "
                         f"temperature, falls below absolute zero where it is carried to the "
                         f"{int(fallback.sum())} without one: too few of the part's points have a temperature "
                         f"to make it cold-equivalent.")
    strain = material.mean_strain(float(trend[0] + centre @ trend[1:]), used)
    cold = points - centre
    cold /= (1 + strain)[:, None]
    cold += centre
    return ColdGeometry(points=cold, temperature=used, fallback=fallback, strain=strain, centre=centre, trend=trend)
