"""The gateway process as configured: which drivers, which patterns, which app."""

from __future__ import annotations

import importlib

import numpy as np
from fastapi import FastAPI

from device_gateway.app import create_app
from device_gateway.station import MultiHeadStation, Station
from services.errors import InputError
from services.formats.sequence import Sequence
from services.settings import Settings
from services.structured_light.patterns import generate_sequence


def build_station(settings: Settings) -> Station | MultiHeadStation:
    """The station of ``settings.station_drivers``, chosen device by device: the simulated forging rig's devices
    (filming ``settings.simulated_scene`` when set), OAK or GenICam cameras, a display projector.

    Raises
    ------
    InputError
        When a driver's package or system library is missing, a GenICam device has no id, or a simulated camera
        is asked to film a real projector.

    With ``settings.simulated_station_heads`` it is the simulated station of that many heads around the hot
    shaft (:func:`device_gateway.drivers.simulated.simulated_station_heads`), every device simulated.
    """
    drivers = settings.station_drivers
    if settings.simulated_station_heads:
        return _simulated_heads(settings)
    if drivers.camera == "simulated" and drivers.projector != "simulated":
        raise InputError("a simulated camera films the simulated projector only: set THERMOFIELD_PROJECTOR_DRIVER="
                         "simulated, or choose a real camera with THERMOFIELD_CAMERA_DRIVER")
    settle_s = None if settings.projector_settle_ms is None else settings.projector_settle_ms / 1000
    simulated = _simulated_station(settings) if "simulated" in drivers else None
    camera = {"simulated": lambda: simulated.camera, "oak": lambda: _oak_camera(settings),
              "genicam": lambda: _genicam_camera(settings)}[drivers.camera]()
    thermal = {"simulated": lambda: simulated.thermal, "oak": lambda: _oak_thermal(settings),
               "genicam": lambda: _genicam_thermal(settings)}[drivers.thermal]()
    projector = simulated.projector if drivers.projector == "simulated" else _display(settings)
    # The simulated rig moves the calibration board only where its own cameras film it; elsewhere a person does.
    holder = simulated if drivers.camera == drivers.thermal == "simulated" else None
    return Station(camera, thermal, projector, settle_s=settle_s, board_holder=holder)


def _simulated_heads(settings: Settings) -> MultiHeadStation:
    from device_gateway.drivers.simulated import simulated_station_heads

    try:
        heads, thermals, _ = simulated_station_heads(settings.simulated_station_heads, settings.simulated_station_scale,
                                                     lose_head=settings.simulated_lost_head)
    except ValueError as error:
        raise InputError(f"THERMOFIELD_SIMULATED_LOST_HEAD: {error}") from None
    return MultiHeadStation(heads, thermals, settle_s=0.0)


def station_sequence_of(settings: Settings, station: Station | MultiHeadStation) -> tuple[Sequence, np.ndarray]:
    """The sequence the gateway projects: a simulated station's of several heads codes its projectors' rows and
    closes with a black frame (``services.simulation.station.station_sequence``); else the default sequence at the
    projector's resolution."""
    if isinstance(station, MultiHeadStation):
        from services.simulation.presets import station_rig
        from services.simulation.station import station_sequence

        return station_sequence(station_rig(settings.simulated_station_scale, settings.simulated_station_heads))
    projector = station.projector.info
    return generate_sequence(projector.width, projector.height, closing_black=settings.hot_part_sequence)


# Drivers are imported on use: depthai, Aravis and SDL load native libraries a simulated station never needs.
def _simulated_station(settings: Settings):
    from device_gateway.drivers.simulated import SimulatedStation
    from services.simulation.scene import load_scene

    scene = None if settings.simulated_scene is None else load_scene(settings.simulated_scene)
    return SimulatedStation(scene=scene, temperatures=None if scene is None else scene.temperature)


def _missing(driver: str, error: ImportError) -> InputError:
    # the gateway extra is left out of the API and worker installs
    return InputError(f"the {driver} driver needs {error.name}, which is not installed: install thermofield "
                      "with its gateway extra, pip install 'thermofield[gateway]'")


def _oak():
    try:
        return importlib.import_module("device_gateway.drivers.oak")
    except ImportError as error:
        raise _missing("oak", error) from None


def _genicam():
    try:
        return importlib.import_module("device_gateway.drivers.genicam")
    except ImportError as error:
        raise _missing("genicam", error) from None
    except ValueError as error:  # gi.require_version: the typelib is not installed
        raise InputError(f"the genicam driver needs Aravis 0.8 ({error}): install Debian's gir1.2-aravis-0.8 "
                         "(make system-libraries)") from None


def _display(settings: Settings):
    try:
        from device_gateway.drivers.display import DisplayProjector
    except ImportError as error:
        raise _missing("display", error) from None
    return DisplayProjector(width=settings.projector_width, height=settings.projector_height,
                            display=settings.projector_display)


def _oak_camera(settings: Settings):
    return _oak().OakCamera(device_id=settings.oak_camera_id, socket=settings.camera_socket,
                            width=settings.camera_width, height=settings.camera_height,
                            exposure_us=settings.camera_exposure_us, iso=settings.camera_iso,
                            lens_position=settings.camera_lens_position)


def _oak_thermal(settings: Settings):
    return _oak().OakThermal(device_id=settings.oak_thermal_id, socket=settings.thermal_socket,
                             gain_mode=settings.thermal_gain_mode)


def _genicam_camera(settings: Settings):
    if not settings.genicam_camera:
        raise InputError("THERMOFIELD_GENICAM_CAMERA: the genicam camera driver needs the camera's Aravis device "
                         "id or IP address (arv-tool-0.8 lists the ids)")
    return _genicam().GenicamCamera(
        device_id=settings.genicam_camera, pixel_format=settings.genicam_pixel_format,
        exposure_us=settings.camera_exposure_us, gain=settings.camera_gain, trigger=settings.genicam_trigger,
        region=(settings.camera_offset_x, settings.camera_offset_y, settings.camera_width, settings.camera_height))


def _genicam_thermal(settings: Settings):
    if not settings.genicam_thermal:
        raise InputError("THERMOFIELD_GENICAM_THERMAL: the genicam thermal driver needs the thermal camera's Aravis "
                         "device id or IP address (arv-tool-0.8 lists the ids)")
    return _genicam().GenicamThermal(device_id=settings.genicam_thermal,
                                     pixel_format=settings.genicam_thermal_pixel_format,
                                     kelvin_per_count=settings.genicam_thermal_kelvin_per_count,
                                     offset_k=settings.genicam_thermal_offset_k)


def create_gateway(settings: Settings, station: Station | None = None) -> FastAPI:
    """The gateway app for ``settings``, projecting the default sequence at the projector's resolution."""
    station = station or build_station(settings)
    sequence, patterns = station_sequence_of(settings, station)
    return create_app(station, sequence, patterns, max_body_bytes=settings.max_body_bytes)
