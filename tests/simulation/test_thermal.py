import numpy as np
import pytest

from services.geometry.camera_model import CameraModel
from services.fusion.radiometry import PlanckConstants, blackbody_counts, blackbody_temperature
from services.simulation.presets import forging_rig, forging_scene
from services.simulation.scene import Plane, Scene, Sphere
from services.simulation.thermal import (
    THERMAL_RANGES,
    Spot, SurfaceTemperature, TemperatureScene, ThermalEffects, forging_temperatures, render_thermal, seen_by,
    surface_temperature,
)

CAMERA = CameraModel(kind="thermal", width=64, height=48, K=[[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
WALL = Plane(center=[0, 0, 500], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[2000, 2000])


def test_surface_fields_are_base_gradient_and_gaussian_spots():
    field = SurfaceTemperature(base=900, gradient=[0.5, 0, 0], origin=[10, 0, 0],
                               spots=[Spot(center=[0, 0, 0], radius=10, amplitude=100)])
    points = np.array([[10.0, 0, 0], [0, 0, 0], [20.0, 0, 1000]])
    expected = [900 + 100 * np.exp(-0.5), 900 - 5 + 100, 905]
    np.testing.assert_allclose(field.evaluate(points), expected)
    scene = TemperatureScene(surfaces=[field], background=30)
    np.testing.assert_allclose(surface_temperature(scene, points, np.array([0, -1, 0])), [expected[0], 30, expected[2]])


def test_uniform_wall_reads_its_temperature_with_the_netd_as_noise():
    temperatures = TemperatureScene(surfaces=[SurfaceTemperature(base=850.0)])
    image = render_thermal(Scene(surfaces=[WALL]), temperatures, CAMERA, ThermalEffects(netd=0.05),
                           np.random.default_rng(0))
    assert image.shape == (48, 64) and image.dtype == np.float32
    assert abs(image.mean() - 850.0) < 0.01
    assert image.std() == pytest.approx(0.05, rel=0.1)


def test_area_integration_mixes_radiance_not_temperature():
    """A pixel 2/5 on a 1000 C plate and 3/5 on 25 C background reads the Planck mean, far above 415 C."""
    boundary_x = (31.9 - 31.5) / 60 * 500  # the plate ends at u = 31.9, between sub-samples of column 32
    scene = Scene(surfaces=[Plane(center=[boundary_x - 500, 0, 500], normal=[0, 0, -1], u_axis=[1, 0, 0],
                                  size=[1000, 2000])])
    temperatures = TemperatureScene(surfaces=[SurfaceTemperature(base=1000.0)], background=25.0)
    effects = ThermalEffects(supersample=5, blur_sigma=0.0, netd=0.0)
    image = render_thermal(scene, temperatures, CAMERA, effects, np.random.default_rng(0))
    constants = PlanckConstants()
    expected = blackbody_temperature(0.4 * blackbody_counts(np.float64(1000.0), constants)
                                     + 0.6 * blackbody_counts(np.float64(25.0), constants), constants)
    assert expected > 0.4 * 1000 + 0.6 * 25 + 50  # well above the mean temperature
    np.testing.assert_allclose(image[:, 32], expected, atol=0.01)
    np.testing.assert_allclose(image[:, :32], 1000.0, atol=1e-6)
    np.testing.assert_allclose(image[:, 33:], 25.0, atol=1e-6)


def test_blur_spreads_the_hot_edge():
    scene = Scene(surfaces=[Plane(center=[-500, 0, 500], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[1000, 2000])])
    temperatures = TemperatureScene(surfaces=[SurfaceTemperature(base=1000.0)], background=25.0)
    sharp = render_thermal(scene, temperatures, CAMERA, ThermalEffects(blur_sigma=0.0, netd=0.0),
                           np.random.default_rng(0))
    blurred = render_thermal(scene, temperatures, CAMERA, ThermalEffects(blur_sigma=1.0, netd=0.0),
                             np.random.default_rng(0))
    assert np.all(blurred[:, 33] > sharp[:, 33] + 100)
    assert np.all(blurred[:, 30] < sharp[:, 30] - 1)


def test_seen_by_tells_hidden_points():
    scene = Scene(surfaces=[WALL, Sphere(center=[0, 0, 300], radius=50)])
    points = np.array([[0.0, 0.0, 500.0], [300.0, 0.0, 500.0], [0.0, 0.0, 250.0]])
    np.testing.assert_array_equal(seen_by(scene, CAMERA, points), [False, True, True])


def test_forging_field_is_hot_with_gradients_and_matches_the_preset_scene():
    scene, temperatures = forging_scene(), forging_temperatures()
    assert len(temperatures.surfaces) == len(scene.surfaces)
    thermal = forging_rig().devices["thermal"]
    image = render_thermal(scene, temperatures, thermal, ThermalEffects(supersample=1), np.random.default_rng(0))
    assert image.shape == (256, 320)
    assert 1050 < image.max() <= 1110
    assert image.min() < 100
    assert np.ptp(image[image > 900]) > 60  # gradients and spots across the part


def test_mismatched_surface_count_is_refused():
    with pytest.raises(ValueError, match="one per surface"):
        render_thermal(Scene(surfaces=[WALL, WALL]), TemperatureScene(surfaces=[SurfaceTemperature(base=20)]),
                       CAMERA, ThermalEffects(), np.random.default_rng(0))


def test_pixels_beyond_the_measuring_range_are_nan_not_clipped():
    temperatures = TemperatureScene(surfaces=[SurfaceTemperature(base=800.0, spots=[
        Spot(center=[0.0, 0.0, 500.0], radius=60.0, amplitude=400.0)])])
    effects = ThermalEffects(netd=0.0, measuring_range=THERMAL_RANGES["tiny1c_low_gain"])
    image = render_thermal(Scene(surfaces=[WALL]), temperatures, CAMERA, effects, np.random.default_rng(0))
    assert np.isnan(image).all()  # 800..1200 C: every pixel beyond the 550 C of the low-gain mode
    forging = ThermalEffects(netd=0.0, measuring_range=THERMAL_RANGES["forging_high_range"])
    image = render_thermal(Scene(surfaces=[WALL]), temperatures, CAMERA, forging, np.random.default_rng(0))
    assert np.isfinite(image).all() and image.max() > 1150
    with pytest.raises(ValueError, match="lowest, highest"):
        ThermalEffects(measuring_range=(500.0, 100.0))
