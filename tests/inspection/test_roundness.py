"""Ovality from points all round a cylinder: the elliptic section's Dmax - Dmin, its direction, and no value from
one side."""

import numpy as np
import pytest

from services.inspection.cylinder import axis_frame, fit_cylinder
from services.inspection.roundness import fit_ovality

pytestmark = pytest.mark.unit

AXIS = np.array([0.96, 0.2, 0.19]) / np.linalg.norm([0.96, 0.2, 0.19])
CENTRE = np.array([5.0, 20.0, 600.0])


def _oval_cylinder(rng, ovality, count=40000, noise=0.02, angle=0.6, half_turn=False, length=200.0):
    """Points of a cylinder of mean diameter 90 whose sections are ellipses with Dmax - Dmin = ``ovality``,
    the largest diameter at ``angle`` in ``axis_frame(AXIS)``."""
    u, v, axis = axis_frame(AXIS)
    theta = rng.uniform(-np.pi / 2, np.pi / 2, count) if half_turn else rng.uniform(-np.pi, np.pi, count)
    s = rng.uniform(-length / 2, length / 2, count)
    a, b = 45.0 + ovality / 4, 45.0 - ovality / 4  # semi-axes: diameters 90 +- ovality / 2
    along_major = a * np.cos(theta)
    along_minor = b * np.sin(theta)
    major = np.cos(angle) * u + np.sin(angle) * v
    minor = -np.sin(angle) * u + np.cos(angle) * v
    points = CENTRE + np.outer(s, axis) + np.outer(along_major, major) + np.outer(along_minor, minor)
    radial = points - CENTRE - np.outer((points - CENTRE) @ axis, axis)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    return points + radial * rng.normal(0.0, noise, count)[:, None]


@pytest.mark.parametrize("ovality", [0.0, 0.12, 0.5])
def test_elliptic_sections(ovality):
    rng = np.random.default_rng(1)
    points = _oval_cylinder(rng, ovality)
    cylinder = fit_cylinder(points, CENTRE + 1.0, AXIS + [0.0, 0.01, -0.01], 44.0)
    assert 2 * cylinder.radius == pytest.approx(90.0, abs=0.005)  # the mean diameter, whatever the ovality
    fit = fit_ovality(points, cylinder.point, cylinder.axis)
    assert len(fit.sections) == 10 and fit.skipped == 0
    assert fit.ovality == pytest.approx(ovality, abs=0.01)
    assert 0 < fit.std < 0.01
    if ovality > 0:
        # the direction of the largest diameter (up to the sign of the fitted axis, which mirrors the angle)
        u, v, _ = axis_frame(cylinder.axis)
        major = np.cos(fit.angle) * u + np.sin(fit.angle) * v
        expected = np.cos(0.6) * axis_frame(AXIS)[0] + np.sin(0.6) * axis_frame(AXIS)[1]
        assert abs(major @ expected) == pytest.approx(1.0, abs=2e-3)


def test_a_dent_is_not_ovality():
    rng = np.random.default_rng(2)
    points = _oval_cylinder(rng, 0.0)
    u, v, axis = axis_frame(AXIS)
    offset = points - CENTRE
    radial = offset - np.outer(offset @ axis, axis)
    unit = radial / np.linalg.norm(radial, axis=1, keepdims=True)
    # a 0.3 mm dent of 4 mm sigma on the side of u, and 3 % of the points thrown 2 mm off
    distance = np.linalg.norm(points - (CENTRE + 45.0 * u), axis=1)
    points = points - unit * (0.3 * np.exp(-distance**2 / 32.0))[:, None]
    stray = rng.choice(len(points), len(points) * 3 // 100, replace=False)
    points[stray] += unit[stray] * rng.normal(0.0, 2.0, len(stray))[:, None]
    fit = fit_ovality(points, CENTRE, AXIS)
    assert fit.ovality < 0.015


def test_one_side_gives_no_ovality():
    rng = np.random.default_rng(3)
    points = _oval_cylinder(rng, 0.3, half_turn=True)
    with pytest.raises(ValueError, match="Ovality needs points all round the cylinder: none of its 10 sections"):
        fit_ovality(points, CENTRE, AXIS)


def test_sections_without_the_whole_circumference_are_left_out():
    rng = np.random.default_rng(4)
    whole = _oval_cylinder(rng, 0.2)
    along = (whole - CENTRE) @ AXIS
    _, v, _ = axis_frame(AXIS)
    # the -s half seen all round, the +s half from one side only
    keep = (along < 0) | ((whole - CENTRE) @ v > 0)
    fit = fit_ovality(whole[keep], CENTRE, AXIS)
    assert fit.skipped == 5 and len(fit.sections) == 5
    assert fit.ovality == pytest.approx(0.2, abs=0.01)


def test_bad_input():
    with pytest.raises(ValueError, match=r"\(N, 3\) array"):
        fit_ovality(np.zeros((10, 2)), CENTRE, AXIS)
    with pytest.raises(ValueError, match="got none"):
        fit_ovality(np.zeros((0, 3)), CENTRE, AXIS)
    with pytest.raises(ValueError, match="section_mm must be positive"):
        fit_ovality(np.zeros((10, 3)), CENTRE, AXIS, section_mm=0)
