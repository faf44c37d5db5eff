"""Cold-equivalent geometry against the simulator's hot part: uniform, gradient and hot-spot fields."""

import numpy as np
import pytest

from services.inspection.cold_equivalent import cold_equivalent
from services.inspection.materials import builtin_material
from services.simulation.hot_part import HotPart, cylinder_mesh
from services.simulation.thermal import Spot, SurfaceTemperature

pytestmark = pytest.mark.integration

STEEL = builtin_material("carbon-steel")


def _hot_and_cold(temperature):
    vertices, triangles = cylinder_mesh(45.0, 200.0, 120)
    part = HotPart(vertices, triangles, STEEL, temperature, centre=(0.0, 0.0, 0.0))
    hot = part.hot_vertices_part()
    measured = part.surface_temperature(hot)
    return vertices, hot, measured


def test_uniform_field_is_exact_scaling():
    cold, hot, temperature = _hot_and_cold(SurfaceTemperature(base=1000.0))
    result = cold_equivalent(hot, temperature, STEEL, centre=np.zeros(3))
    assert np.abs(result.points - cold).max() < 1e-9
    assert 2 * np.hypot(hot[:, 1], hot[:, 2]).max() == pytest.approx(91.242)
    assert not result.fallback.any()


def test_gradient_is_exact_where_a_uniform_scaling_is_not():
    cold, hot, temperature = _hot_and_cold(SurfaceTemperature(base=1000.0, gradient=[0.3, 0.0, 0.0]))
    result = cold_equivalent(hot, temperature, STEEL, centre=np.zeros(3))
    uniform = cold_equivalent(hot, np.full(len(hot), np.mean(temperature)), STEEL, centre=np.zeros(3))
    assert np.linalg.norm(result.points - cold, axis=1).max() < 1e-4
    assert np.linalg.norm(uniform.points - cold, axis=1).max() > 0.02


def test_hot_spot_interior_is_modelled_not_measured():
    # the simulator's spot heats the interior too; the model sees only the surface, so the points whose
    # segment from the centre passes the spot's core keep an error of a few hundredths of a millimetre
    field = SurfaceTemperature(base=1000.0, spots=[Spot(center=[40.0, 0.0, 45.0], radius=20.0, amplitude=60.0)])
    cold, hot, temperature = _hot_and_cold(field)
    error = np.linalg.norm(cold_equivalent(hot, temperature, STEEL, centre=np.zeros(3)).points - cold, axis=1)
    assert 0.005 < error.max() < 0.035
    assert np.median(error) < 0.002


def test_points_without_temperature_use_the_trend_and_are_flagged():
    cold, hot, temperature = _hot_and_cold(SurfaceTemperature(base=950.0, gradient=[0.2, 0.0, 0.0]))
    missing = np.zeros(len(hot), dtype=bool)
    missing[::7] = True
    result = cold_equivalent(hot, np.where(missing, np.nan, temperature), STEEL, centre=np.zeros(3))
    assert (result.fallback == missing).all()
    assert result.temperature[missing] == pytest.approx(temperature[missing], abs=0.5)
    assert np.linalg.norm(result.points - cold, axis=1).max() < 0.005
    with pytest.raises(ValueError, match="at least 4 are needed"):
        cold_equivalent(hot[:3], np.full(3, np.nan), STEEL)


def test_points_without_a_temperature_take_their_neighbourhood_s_not_the_trend_s():
    """A hot spot the trend does not follow: a point inside it without a reading gets the spot's temperature."""
    from services.inspection.cold_equivalent import neighbourhood_temperature, temperature_trend

    rng = np.random.default_rng(0)
    points = rng.uniform(-100.0, 100.0, (20000, 3))
    points[:, 2] = 0.0
    temperature = 1000.0 + 0.2 * points[:, 0] + 80.0 * np.exp(-np.sum((points - [50.0, 0.0, 0.0]) ** 2, axis=1)
                                                              / (2 * 15.0**2))
    truth = temperature.copy()
    missing = np.flatnonzero(np.linalg.norm(points - [50.0, 0.0, 0.0], axis=1) < 4.0)  # the spot's core
    temperature[missing] = np.nan
    trend = temperature_trend(points, temperature)
    estimated = neighbourhood_temperature(points, temperature, trend, missing)
    assert np.max(np.abs(estimated - truth[missing])) < 6.0
    assert np.min(np.abs(points[missing] @ trend[1:] + trend[0] - truth[missing])) > 40.0  # the trend alone: not
    far = np.array([[500.0, 500.0, 0.0]])
    alone = neighbourhood_temperature(np.vstack([points, far]), np.append(temperature, np.nan), trend,
                                      np.array([len(points)]))
    assert alone[0] == pytest.approx(far[0] @ trend[1:] + trend[0])  # nobody within 25 mm: the trend


def test_a_trend_carried_below_absolute_zero_is_refused_in_a_sentence():
    """A few readings clustered at one end of a long part, falling 20 K a millimetre: carried to the far end the
    trend gives temperatures below absolute zero, which is no reason to make the part cold-equivalent."""
    points = np.column_stack([np.linspace(0.0, 300.0, 301), np.zeros(301), np.zeros(301)])
    points[:, 1] = np.sin(points[:, 0])  # not all on a line: the trend's fit is well posed
    points[:, 2] = np.cos(points[:, 0] / 7.0)
    temperature = np.full(301, np.nan)
    temperature[:20] = 1000.0 - 20.0 * points[:20, 0]
    with pytest.raises(ValueError, match="falls below absolute zero .* too few of the part's points have a temperature"):
        cold_equivalent(points, temperature, STEEL)
