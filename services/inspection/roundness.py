"""Ovality of a cylinder measured all round: the spread of its two-point diameters, cross-section by cross-section."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.inspection.cylinder import axis_frame
from services.inspection.robust import robust_scale, tukey_weights

SECTION_MM = 20.0
SECTORS = 8
MIN_SECTOR_POINTS = 5
_ITERATIONS = 5


@dataclass(frozen=True)
class OvalityFit:
    """The ovality of the worst cross-section and how it was found.

    Attributes
    ----------
    ovality : float
        Dmax - Dmin of the section with the largest one, mm.
    std : float
        Its standard deviation from the points' noise, mm.
    angle : float
        Direction of that section's largest diameter about the axis, radians in [0, pi), measured in the
        frame of :func:`services.inspection.cylinder.axis_frame`.
    sections : (K,) array
        The ovality of every section that was measured, mm, in order along the axis.
    skipped : int
        Sections holding points that do not go all round (left out).
    """

    ovality: float
    std: float
    angle: float
    sections: np.ndarray
    skipped: int


def fit_ovality(points: np.ndarray, axis_point: np.ndarray, axis: np.ndarray, section_mm: float = SECTION_MM,
                sectors: int = SECTORS, min_sector_points: int = MIN_SECTOR_POINTS) -> OvalityFit:
    """The ovality (Dmax - Dmin) of a cylinder from points all round it, about a fitted axis.

    Parameters
    ----------
    points : (N, 3) array
        Points of the cylinder's surface, mm.
    axis_point, axis : (3,) arrays
        A point on the cylinder's axis and its direction (a least-squares cylinder's, e.g. ``fit_cylinder``).
    section_mm : float
        Length along the axis of each cross-section (slab) whose profile is fitted.
    sectors : int
        A section counts only if each of this many equal angular sectors about the axis holds at least
        ``min_sector_points`` of its points: ovality needs the whole circumference, not one side.
    min_sector_points : int
        See ``sectors``.

    Returns
    -------
    OvalityFit
        The worst section's ovality, its standard deviation and direction, and every section's value.

    Raises
    ------
    ValueError
        When no section has points all round (a one-sided view), or the inputs are malformed.

    Notes
    -----
    In the frame (u, v, a) of the axis each point has the angle theta and radius r about the axis and
    the position s along it. The points are cut into slabs of ``section_mm`` along s, and in each the
    radial profile is fitted by least squares up to the second harmonic,

        r(theta) = r0 + a1 cos(theta) + b1 sin(theta) + a2 cos(2 theta) + b2 sin(2 theta),

    with Tukey's biweight (4.685 robust sigmas, five reweightings) so that a dent or stray points do not
    pull it. The first harmonic is the section's centre off the axis (a bent or offset section), which
    a two-point diameter does not see. The two-point diameter of the fitted profile is
    d(theta) = r(theta) + r(theta + pi) = 2 r0 + 2 (a2 cos 2 theta + b2 sin 2 theta) (odd harmonics
    cancel), so

        ovality = Dmax - Dmin = 4 sqrt(a2^2 + b2^2),

    the out-of-roundness of pipe standards (API 5L, 9.2.3: the difference between the largest and
    smallest outside diameters in one cross-section) evaluated on the least-squares profile instead of
    the noisy extreme points, which would add several noise sigmas. It is the two-undulations-per-
    revolution component of roundness; the ISO 12181-1 least-squares roundness deviation (peak to
    valley about the least-squares circle) includes every harmonic and the noise and is not this
    measure. The part's ovality is its worst section's (a tolerance holds in every cross-section); its
    standard deviation is 4 sqrt((a2^2 var(a2) + b2^2 var(b2) + 2 a2 b2 cov) / (a2^2 + b2^2)) from
    s^2 (A^T W A)^-1 of that section's fit. With noise alone the magnitude is biased upward by about
    1.25 times that deviation (a Rayleigh mean), micrometres for the thousands of points of a section.

    References
    ----------
    .. [1] ISO 12181-1:2011, Geometrical product specifications (GPS) -- Roundness -- Part 1:
       Vocabulary and parameters of roundness (least-squares reference circle, undulations per
       revolution).
    .. [2] API Specification 5L, 46th ed. (2018), 9.2.3, out-of-roundness.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"The points must be an (N, 3) array; got shape {points.shape}.")
    if not section_mm > 0 or sectors < 4 or min_sector_points < 1:
        raise ValueError(f"section_mm must be positive, sectors at least 4 and min_sector_points at least 1; got "
                         f"{section_mm}, {sectors}, {min_sector_points}.")
    if len(points) == 0:
        raise ValueError("Ovality needs points all round the cylinder; got none.")
    frame = axis_frame(np.asarray(axis, dtype=np.float64))
    local = (points - np.asarray(axis_point, dtype=np.float64)) @ frame.T
    theta = np.arctan2(local[:, 1], local[:, 0])
    radius = np.hypot(local[:, 0], local[:, 1])
    along = local[:, 2]
    section = np.floor((along - along.min()) / section_mm).astype(np.intp)
    sector = np.minimum((theta + np.pi) / (2 * np.pi) * sectors, sectors - 1).astype(np.intp)
    values, stds, angles = [], [], []
    skipped = 0
    for index in np.unique(section):
        inside = section == index
        if np.bincount(sector[inside], minlength=sectors).min() < min_sector_points:
            skipped += 1
            continue
        value, std, angle = _section_ovality(theta[inside], radius[inside])
        values.append(value)
        stds.append(std)
        angles.append(angle)
    if not values:
        raise ValueError(f"Ovality needs points all round the cylinder: none of its {skipped} sections of "
                         f"{section_mm:g} mm has at least {min_sector_points} points in each of {sectors} sectors "
                         "about the axis (a view of one side).")
    worst = int(np.argmax(values))
    return OvalityFit(ovality=values[worst], std=stds[worst], angle=angles[worst], sections=np.asarray(values),
                      skipped=skipped)


def _section_ovality(theta: np.ndarray, radius: np.ndarray) -> tuple[float, float, float]:
    """One section's 4 |c2|, its standard deviation and the direction of its largest diameter (IRLS)."""
    design = np.column_stack([np.ones_like(theta), np.cos(theta), np.sin(theta), np.cos(2 * theta),
                              np.sin(2 * theta)])
    weights = np.ones_like(theta)
    for _ in range(_ITERATIONS):
        root = np.sqrt(weights)
        coefficients = np.linalg.lstsq(design * root[:, None], radius * root, rcond=None)[0]
        residual = radius - design @ coefficients
        scale = robust_scale(residual)
        weights = tukey_weights(residual, scale)
    normal = design.T @ (design * weights[:, None])
    covariance = np.linalg.pinv(normal) * scale**2
    a2, b2 = coefficients[3:5]
    magnitude = float(np.hypot(a2, b2))
    if magnitude > 0:
        gradient = np.array([a2, b2]) / magnitude
        variance = float(gradient @ covariance[3:5, 3:5] @ gradient)
    else:
        variance = float(np.trace(covariance[3:5, 3:5]) / 2)
    angle = float(np.arctan2(b2, a2) / 2) % np.pi
    return 4 * magnitude, 4 * float(np.sqrt(max(variance, 0.0))), angle
