"""Fitting a part file's features to measured points: plane, cylinder and sphere fits started from the nominal."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.formats.part import Feature
from services.inspection.cylinder import fit_cylinder
from services.inspection.distance import Element
from services.inspection.nominal import NominalSurface
from services.inspection.plane import PlaneFit, fit_plane
from services.inspection.roundness import fit_ovality
from services.inspection.sphere import SphereFit, fit_sphere

MIN_FEATURE_POINTS = 20


@dataclass(frozen=True)
class NominalFeature:
    """A feature fitted to the nominal surface's samples in its region: the start of the measured fits."""

    feature: Feature
    element: Element


def fit_nominal_feature(feature: Feature, nominal: NominalSurface) -> NominalFeature:
    """Fit a plane, cylinder or sphere feature to the nominal mesh's surface samples in its region."""
    inside = feature.region.contains(nominal.samples)
    points, normals = nominal.samples[inside], nominal.sample_normals[inside]
    if len(points) < MIN_FEATURE_POINTS:
        raise ValueError(f"feature {feature.name!r}: its region holds only {len(points)} samples of the nominal "
                         "surface; does the box enclose the surface it means?")
    if feature.type == "plane":
        return NominalFeature(feature, fit_plane(points))
    if feature.type == "sphere":
        return NominalFeature(feature, fit_sphere(points))
    # a cylinder's axis is perpendicular to all its normals: the normals' least principal direction
    _, vectors = np.linalg.eigh(normals.T @ normals)
    axis = vectors[:, 0]
    centre = points.mean(axis=0)
    offset = points - centre
    radius = float(np.mean(np.linalg.norm(offset - np.outer(offset @ axis, axis), axis=1)))
    # the centroid of a partial surface lies off the axis: a first fit finds the axis, a second polishes it
    first = fit_cylinder(points, centre - radius * _mean_normal(normals, axis), axis, radius)
    return NominalFeature(feature, fit_cylinder(points, first.point, first.axis, first.radius))


def _mean_normal(normals: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The mean normal across the axis (zero for a full cylinder: its centroid is on the axis)."""
    mean = normals.mean(axis=0)
    mean -= (mean @ axis) * axis
    return mean


def fit_measured(nominal: NominalFeature, points: np.ndarray, stretch: float = 1.0) -> Element:
    """Fit the feature to measured points (part frame), started from the nominal element scaled by ``stretch``."""
    if len(points) < MIN_FEATURE_POINTS:
        raise ValueError(f"feature {nominal.feature.name!r}: only {len(points)} measured points in its region "
                         f"(at least {MIN_FEATURE_POINTS} are needed)")
    element = nominal.element
    if isinstance(element, PlaneFit):
        return fit_plane(points)
    if isinstance(element, SphereFit):
        return fit_sphere(points)
    return fit_cylinder(points, element.point, element.axis, element.radius * stretch)


@dataclass(frozen=True)
class Measured:
    """A feature's measure from its fitted element: the value and its own standard deviation (the points'
    random noise through the fit), mm."""

    value: float
    std: float


def measure(feature: Feature, element: Element, points: np.ndarray) -> Measured:
    """The measure a feature names, from its fitted element and the points it was fitted to (part frame).

    ``ovality`` fits the cross-sections' profiles about the element's axis (``fit_ovality``; a
    ``ValueError`` when the points do not go all round); the other measures read the element.
    """
    if feature.measure == "diameter":
        return Measured(2 * element.radius, 2 * element.radius_std)
    if feature.measure == "ovality":
        roundness = fit_ovality(points, element.point, element.axis)
        return Measured(roundness.ovality, roundness.std)
    return Measured(float(getattr(element, feature.measure)), element.noise)  # flatness, cylindricity, sphericity


def element_position_std(element: Element) -> float:
    """Standard deviation of an element's position (plane along its normal, axis or centre)."""
    return element.point_std if isinstance(element, PlaneFit) else element.radius_std

