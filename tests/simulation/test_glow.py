import json

import numpy as np
import pytest

from services.errors import InputError
from services.geometry.camera_model import CameraModel
from services.simulation.glow import expose_sensor, render_glow_view, render_hot_frames
from services.simulation.optics import SensorOptics
from services.simulation.presets import hot_optics
from services.simulation.render import render_view
from services.simulation.scene import Plane, Scene, parse_scene
from services.simulation.temperature import SurfaceTemperature, TemperatureScene

pytestmark = pytest.mark.integration

PROJECTOR = CameraModel(kind="projector", width=64, height=48, K=[[60, 0, 31.5], [0, 60, 23.5], [0, 0, 1]])
CAMERA = CameraModel(kind="camera", width=32, height=24, K=[[30, 0, 15.5], [0, 30, 11.5], [0, 0, 1]],
                R=np.eye(3).tolist(), t=[-20.0, 0.0, 0.0])
WALL = Plane(center=[0, 0, 500], normal=[0, 0, -1], u_axis=[1, 0, 0], size=[2000, 2000])


def _hot_wall(temperature_c: float, cooling_rate: float = 0.0) -> Scene:
    return Scene(surfaces=[WALL], ambient=0.0, optics=hot_optics("white"),
                 temperature=TemperatureScene(surfaces=[SurfaceTemperature(base=temperature_c,
                                                                           cooling_rate=cooling_rate)]))


def test_sensor_noise_is_shot_noise_plus_read_noise_in_grey_levels():
    sensor = SensorOptics(full_well_e=10000.0, read_noise_e=5.0, bit_depth=12)
    rate, exposure = 1e7, 1e-4  # 1000 electrons at irradiance 1
    frames = np.stack([expose_sensor(np.full((64, 64), 2.0), sensor, rate, exposure, np.random.default_rng(seed))
                       for seed in range(8)]).astype(np.float64)
    gain = sensor.gain_e_per_dn
    assert frames.mean() == pytest.approx(2000 / gain, rel=0.01)
    assert frames.var() == pytest.approx((2000 + 25) / gain**2 + 1 / 12, rel=0.05)


def test_sensor_saturates_at_its_full_well_and_bit_depth():
    for bits, dtype in ((8, np.uint8), (10, np.uint16), (12, np.uint16)):
        sensor = SensorOptics(bit_depth=bits)
        frame = expose_sensor(np.array([[0.0, 1e6]]), sensor, 1e7, 1e-3, np.random.default_rng(0))
        assert frame.dtype == dtype and frame[0, 1] == (1 << bits) - 1 and frame[0, 0] <= 1
    with pytest.raises(ValueError, match="exposure time must be positive"):
        expose_sensor(np.zeros((2, 2)), SensorOptics(), 1e7, 0.0, np.random.default_rng(0))


def test_glow_grows_with_temperature_and_fades_as_the_part_cools():
    black = np.zeros((1, PROJECTOR.height, PROJECTOR.width), np.uint8)
    scene = _hot_wall(1100.0, cooling_rate=20.0)
    view = render_view(scene, CAMERA, PROJECTOR, 1)
    glow = render_glow_view(scene, CAMERA, 1)
    optics = scene.optics
    exposure = 0.5 * optics.sensor.full_well_e / (optics.white_rate * float(optics.relative_glow(1100.0)))
    frames = np.stack([render_hot_frames(view, glow, black, exposure, np.random.default_rng(0), start_s=start)[0]
                       for start in (0.0, 1.0)]).astype(np.float64)
    expected = optics.relative_glow(np.array([1100.0, 1080.0])) * optics.white_rate * exposure \
        / optics.sensor.gain_e_per_dn
    np.testing.assert_allclose(frames.mean(axis=(1, 2)), expected, rtol=0.01)
    assert frames[1].mean() < 0.9 * frames[0].mean()


def test_scene_file_carries_temperature_and_optics():
    text = json.dumps({"surfaces": [{"type": "plane", "center": [0, 0, 500], "normal": [0, 0, -1],
                                     "u_axis": [1, 0, 0], "size": [100, 100]}],
                       "temperature": {"surfaces": [{"base": 1150, "cooling_rate": 3}]},
                       "optics": {"version": 1, "projector": {"spectrum": "blue_led"},
                                  "camera_filter": {"centre_nm": 450, "fwhm_nm": 40}}})
    scene = parse_scene(text, "hot.json")
    assert scene.temperature.surfaces[0].cooling_rate == 3 and scene.optics.camera_filter.fwhm_nm == 40
    assert parse_scene(scene.model_dump_json(), "again.json") == scene
    two_fields = text.replace('[{"base": 1150, "cooling_rate": 3}]', '[{"base": 1150}, {"base": 40}]')
    with pytest.raises(InputError, match="hot.json.*2 surface fields for 1 surfaces"):
        parse_scene(two_fields, "hot.json")
    with pytest.raises(InputError, match="hot.json: optics.version"):
        parse_scene(text.replace('"version": 1', '"version": 2'), "hot.json")


def test_a_scene_without_temperature_does_not_glow():
    with pytest.raises(ValueError, match="lacks temperature"):
        render_glow_view(Scene(surfaces=[WALL], optics=hot_optics()), CAMERA, 1)
