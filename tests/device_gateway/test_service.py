"""The gateway as configured: settings choose the drivers and their options."""

from __future__ import annotations

import sys

import depthai as dai
import pytest

from device_gateway.drivers.display import DisplayProjector
from device_gateway.drivers.oak import OakCamera, OakThermal
from device_gateway.service import build_station, create_gateway
from services.errors import InputError
from services.settings import Settings


def test_simulated_driver_is_the_forging_station():
    station = build_station(Settings(gateway_driver="simulated"))
    infos = [device.info for device in station.devices]
    assert [(info.name, info.kind, info.driver) for info in infos] == [
        ("camera", "camera", "simulated"), ("thermal", "thermal", "simulated"), ("projector", "projector", "simulated")]
    assert [(info.width, info.height) for info in infos] == [(1280, 800), (320, 256), (1280, 800)]
    assert station.settle_s == 0.0


def test_oak_driver_takes_its_options_from_the_settings():
    settings = Settings(gateway_driver="oak", oak_camera_id="14442C10D13EABCE00", oak_thermal_id="10.0.0.7",
                        camera_exposure_us=4000, camera_iso=200, camera_width=1920, camera_height=1200,
                        projector_display=1, projector_width=1920, projector_height=1080, projector_settle_ms=250)
    station = build_station(settings)
    assert isinstance(station.camera, OakCamera) and isinstance(station.thermal, OakThermal)
    assert isinstance(station.projector, DisplayProjector)
    camera = station.camera
    assert (camera.device_id, camera.exposure_us, camera.iso) == ("14442C10D13EABCE00", 4000, 200)
    assert (station.camera.info.width, station.camera.info.height) == (1920, 1200)
    assert station.thermal.device_id == "10.0.0.7"
    assert (camera.socket, camera.lens_position) == (dai.CameraBoardSocket.CAM_A, 130)
    assert (station.thermal.socket, station.thermal.gain_mode) == (dai.CameraBoardSocket.CAM_E, "low")
    assert (station.projector.display, station.projector.info.width, station.projector.info.height) == (1, 1920, 1080)
    assert station.settle_s == 0.25


def test_gateway_projects_the_default_sequence_at_the_projector_size(station, small_rig):
    app = create_gateway(Settings(), station=station)
    paths = {route.path for route in app.routes}
    assert {"/healthz", "/v1/devices", "/v1/sequence", "/v1/captures"} <= paths
    operations = {route.operation_id for route in app.routes if getattr(route, "operation_id", None)}
    assert operations == {"health", "listDevices", "getSequence", "capture", "boardViews"}
    sequence_route = next(route for route in app.routes if route.path == "/v1/sequence")
    sequence = sequence_route.endpoint()
    projector = small_rig.devices["projector"]
    assert (sequence.projector.width, sequence.projector.height) == (projector.width, projector.height)


def test_sockets_focus_and_gain_are_settings():
    station = build_station(Settings(gateway_driver="oak", camera_socket="CAM_B", camera_lens_position=90,
                                     thermal_socket="CAM_C", thermal_gain_mode="high"))
    assert (station.camera.socket, station.camera.lens_position) == (dai.CameraBoardSocket.CAM_B, 90)
    assert (station.thermal.socket, station.thermal.gain_mode) == (dai.CameraBoardSocket.CAM_C, "high")


def test_without_the_gateway_extra_the_oak_driver_says_what_to_install(monkeypatch):
    for module in ("device_gateway.drivers.oak", "device_gateway.drivers.display"):
        monkeypatch.delitem(sys.modules, module, raising=False)
    monkeypatch.setitem(sys.modules, "depthai", None)  # as if depthai were not installed
    with pytest.raises(InputError, match=r"needs depthai.*thermofield\[gateway\]"):
        build_station(Settings(gateway_driver="oak"))


def test_the_simulated_driver_films_the_scene_file_of_the_settings(tmp_path):
    from services.simulation.presets import hot_optics, hot_part_scene

    scene = hot_part_scene(1000.0, hot_optics("white"))
    path = tmp_path / "hot-part.json"
    path.write_text(scene.model_dump_json())
    station = build_station(Settings(gateway_driver="simulated", simulated_scene=path))
    simulated = station.board_holder  # the SimulatedStation behind the devices
    assert simulated.hot and simulated.scene == scene and simulated.temperatures == scene.temperature


def test_a_bad_scene_file_is_named(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text('{"surfaces": []}')
    with pytest.raises(InputError, match="scene.json"):
        build_station(Settings(gateway_driver="simulated", simulated_scene=path))


def test_drivers_are_chosen_per_device():
    from device_gateway.drivers.genicam import GenicamCamera, GenicamThermal

    settings = Settings(camera_driver="genicam", genicam_camera="Basler-acA1920-40gm-40012345",
                        genicam_pixel_format="Mono12", genicam_trigger="Line1", camera_gain=6.0,
                        camera_offset_x=64, camera_offset_y=32, camera_width=1920, camera_height=1200,
                        camera_exposure_us=3000, thermal_driver="genicam", genicam_thermal="192.168.10.20",
                        genicam_thermal_kelvin_per_count=0.1, genicam_thermal_offset_k=-10.0)
    assert tuple(settings.station_drivers) == ("genicam", "genicam", "simulated")
    station = build_station(settings)
    camera, thermal = station.camera, station.thermal
    assert isinstance(camera, GenicamCamera) and isinstance(thermal, GenicamThermal)
    assert (camera.device_id, camera.format.name, camera.trigger, camera.gain, camera.exposure_us) == (
        "Basler-acA1920-40gm-40012345", "Mono12", "Line1", 6.0, 3000)
    assert camera.region == (64, 32, 1920, 1200) and camera.saturation_level == 4095
    assert (thermal.device_id, thermal.format.name, thermal.kelvin_per_count, thermal.offset_k, thermal.trigger) == (
        "192.168.10.20", "Mono16", 0.1, -10.0, None)
    assert station.projector.info.driver == "simulated" and station.board_holder is None

    mixed = build_station(Settings(gateway_driver="oak", thermal_driver="simulated"))
    assert [device.info.driver for device in mixed.devices] == ["oak", "simulated", "display"]


def test_the_gateway_driver_stands_for_every_device():
    assert tuple(Settings(gateway_driver="genicam").station_drivers) == ("genicam", "genicam", "display")
    assert tuple(Settings(gateway_driver="oak").station_drivers) == ("oak", "oak", "display")
    assert tuple(Settings().station_drivers) == ("simulated", "simulated", "simulated")


@pytest.mark.parametrize(("settings", "message"), [
    ({"camera_driver": "genicam"}, "THERMOFIELD_GENICAM_CAMERA: the genicam camera driver needs"),
    ({"thermal_driver": "genicam"}, "THERMOFIELD_GENICAM_THERMAL"),
    ({"projector_driver": "display"}, "a simulated camera films the simulated projector only"),
])
def test_an_incomplete_choice_of_drivers_is_refused_naming_the_setting(settings, message):
    with pytest.raises(InputError, match=message):
        build_station(Settings(**settings))


def test_without_aravis_the_genicam_driver_says_what_to_install(monkeypatch):
    monkeypatch.delitem(sys.modules, "device_gateway.drivers.genicam", raising=False)
    monkeypatch.setitem(sys.modules, "gi", None)  # as if PyGObject were not installed
    with pytest.raises(InputError, match=r"the genicam driver needs gi.*thermofield\[gateway\]"):
        build_station(Settings(camera_driver="genicam", genicam_camera="x"))
