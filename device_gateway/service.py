"""The gateway process as configured: which drivers, which patterns, which app."""

from __future__ import annotations

from fastapi import FastAPI

from device_gateway.app import create_app
from device_gateway.station import Station
from services.settings import Settings
from services.structured_light.patterns import generate_sequence


def build_station(settings: Settings) -> Station:
    """The station of ``settings.gateway_driver``: the simulated forging rig, or OAK cameras and a display."""
    settle_s = None if settings.projector_settle_ms is None else settings.projector_settle_ms / 1000
    # Drivers are imported on use: depthai and SDL load native libraries a simulated station never needs.
    if settings.gateway_driver == "simulated":
        from device_gateway.drivers.simulated import SimulatedStation

        simulated = SimulatedStation()
        return Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=settle_s,
                       board_holder=simulated)
    from device_gateway.drivers.display import DisplayProjector
    from device_gateway.drivers.oak import OakCamera, OakThermal

    return Station(
        OakCamera(device_id=settings.oak_camera_id, width=settings.camera_width, height=settings.camera_height,
                  exposure_us=settings.camera_exposure_us, iso=settings.camera_iso),
        OakThermal(device_id=settings.oak_thermal_id),
        DisplayProjector(width=settings.projector_width, height=settings.projector_height,
                         display=settings.projector_display),
        settle_s=settle_s,
    )


def create_gateway(settings: Settings, station: Station | None = None) -> FastAPI:
    """The gateway app for ``settings``, projecting the default sequence at the projector's resolution."""
    station = station or build_station(settings)
    projector = station.projector.info
    sequence, patterns = generate_sequence(projector.width, projector.height, closing_black=settings.hot_part_sequence)
    return create_app(station, sequence, patterns)
