"""The gateway process as configured: which drivers, which patterns, which app."""

from __future__ import annotations

from fastapi import FastAPI

from device_gateway.app import create_app
from device_gateway.station import Station
from services.errors import InputError
from services.settings import Settings
from services.structured_light.patterns import generate_sequence


def build_station(settings: Settings) -> Station:
    """The station of ``settings.gateway_driver``: the simulated forging rig (filming ``settings.simulated_scene``
    when set), or OAK cameras and a display."""
    settle_s = None if settings.projector_settle_ms is None else settings.projector_settle_ms / 1000
    # Drivers are imported on use: depthai and SDL load native libraries a simulated station never needs.
    if settings.gateway_driver == "simulated":
        from device_gateway.drivers.simulated import SimulatedStation
        from services.simulation.scene import load_scene

        scene = None if settings.simulated_scene is None else load_scene(settings.simulated_scene)
        simulated = SimulatedStation(scene=scene, temperatures=None if scene is None else scene.temperature)
        return Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=settle_s,
                       board_holder=simulated)
    try:
        from device_gateway.drivers.display import DisplayProjector
        from device_gateway.drivers.oak import OakCamera, OakThermal
    except ImportError as error:  # the gateway extra is left out of the API and worker installs
        raise InputError(f"the oak driver needs {error.name}, which is not installed: install thermofield "
                         "with its gateway extra, pip install 'thermofield[gateway]'") from None

    return Station(
        OakCamera(device_id=settings.oak_camera_id, socket=settings.camera_socket, width=settings.camera_width,
                  height=settings.camera_height, exposure_us=settings.camera_exposure_us, iso=settings.camera_iso,
                  lens_position=settings.camera_lens_position),
        OakThermal(device_id=settings.oak_thermal_id, socket=settings.thermal_socket,
                   gain_mode=settings.thermal_gain_mode),
        DisplayProjector(width=settings.projector_width, height=settings.projector_height,
                         display=settings.projector_display),
        settle_s=settle_s,
    )


def create_gateway(settings: Settings, station: Station | None = None) -> FastAPI:
    """The gateway app for ``settings``, projecting the default sequence at the projector's resolution."""
    station = station or build_station(settings)
    projector = station.projector.info
    sequence, patterns = generate_sequence(projector.width, projector.height, closing_black=settings.hot_part_sequence)
    return create_app(station, sequence, patterns, max_body_bytes=settings.max_body_bytes)
