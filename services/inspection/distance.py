"""Distances between fitted features: planes, cylinder axes and sphere centres."""

from __future__ import annotations

import numpy as np

from services.inspection.cylinder import CylinderFit
from services.inspection.plane import PlaneFit
from services.inspection.sphere import SphereFit

Element = PlaneFit | CylinderFit | SphereFit


def _point_line(point: np.ndarray, line_point: np.ndarray, direction: np.ndarray) -> float:
    offset = point - line_point
    return float(np.linalg.norm(offset - (offset @ direction) * direction))


def feature_distance(first: Element, second: Element) -> float:
    """The distance users mean between two fitted features, mm.

    Parameters
    ----------
    first, second : PlaneFit, CylinderFit or SphereFit
        Fitted elements.

    Returns
    -------
    distance : float

    Notes
    -----
    Plane to plane (nominally parallel faces): the mean of each plane's centre's distance from the
    other, (|n_1 . (c_2 - c_1)| + |n_2 . (c_1 - c_2)|) / 2, which is symmetric and insensitive to a
    small tilt. Plane to cylinder or sphere: the distance of the axis point or centre from the
    plane. Cylinder to cylinder: the distance between the axes (of the second's axis point from the
    first's axis, averaged both ways); to a sphere: of the centre from the axis. Sphere to sphere:
    between centres. This follows ISO 14405-2's practice of measuring between associated
    (least-squares) features.
    """
    kinds = (type(first), type(second))
    if kinds == (PlaneFit, PlaneFit):
        offset = second.point - first.point
        return float((abs(first.normal @ offset) + abs(second.normal @ offset)) / 2)
    if PlaneFit in kinds:
        plane, other = (first, second) if isinstance(first, PlaneFit) else (second, first)
        point = other.center if isinstance(other, SphereFit) else other.point
        return float(abs(plane.normal @ (point - plane.point)))
    if kinds == (CylinderFit, CylinderFit):
        return (_point_line(second.point, first.point, first.axis)
                + _point_line(first.point, second.point, second.axis)) / 2
    if CylinderFit in kinds:
        cylinder, sphere = (first, second) if isinstance(first, CylinderFit) else (second, first)
        return _point_line(sphere.center, cylinder.point, cylinder.axis)
    return float(np.linalg.norm(first.center - second.center))
