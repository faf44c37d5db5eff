"""A quarter-resolution forging station (tracing its view takes a fraction of a second), and device faults."""

from __future__ import annotations

import socket

import numpy as np
import pytest

from device_gateway.devices import CameraDriver, DeviceInfo, DeviceLost, DeviceUnavailable, Frame
from device_gateway.drivers.simulated import SimulatedStation
from device_gateway.station import Station
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.simulation import presets
from services.structured_light.patterns import generate_sequence

SCALE = 4


def _downscaled(device: CameraModel, scale: int) -> CameraModel:
    K = device.K.copy()
    K[:2, :2] /= scale
    K[:2, 2] = (K[:2, 2] + 0.5) / scale - 0.5  # pixel centres at integers
    return device.replace(**{"width": device.width // scale, "height": device.height // scale,
                                     "K": K.tolist()})


@pytest.fixture(scope="session")
def small_rig() -> Rig:
    rig = presets.forging_rig()
    return Rig(devices={name: _downscaled(device, SCALE) for name, device in rig.devices.items()})


@pytest.fixture(scope="session")
def simulated(small_rig) -> SimulatedStation:
    """Shared across tests: the traced view is computed once per session."""
    return SimulatedStation(rig=small_rig)


@pytest.fixture
def station(simulated) -> Station:
    station = Station(simulated.camera, simulated.thermal, simulated.projector)
    yield station
    station.close()


@pytest.fixture(scope="session")
def sequence_and_patterns(small_rig):
    projector = small_rig.devices["projector"]
    return generate_sequence(projector.width, projector.height)


@pytest.fixture(scope="session")
def lit(simulated) -> np.ndarray:
    """Camera pixels the projector lights, from the simulator's ground truth."""
    return simulated.view().truth.lit


@pytest.fixture
def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Unplugged(CameraDriver):
    """A camera lost at its ``fail_at``-th grab, which then stays away for ``away`` openings."""

    def __init__(self, camera: CameraDriver, fail_at: int, away: int = 0) -> None:
        self.camera, self.fail_at, self.away = camera, fail_at, away
        self.grabs = self.opens = 0

    @property
    def info(self) -> DeviceInfo:
        return self.camera.info

    @property
    def is_open(self) -> bool:
        return self.camera.is_open

    def open(self) -> None:
        self.opens += 1
        if self.grabs >= self.fail_at and self.away > 0:
            self.away -= 1
            raise DeviceUnavailable("camera 'camera': not connected")
        self.camera.open()

    def close(self) -> None:
        self.camera.close()

    def grab(self, timeout_s: float) -> Frame:
        self.grabs += 1
        if self.grabs == self.fail_at:
            self.camera.close()
            raise DeviceLost("camera 'camera': connection lost")
        return self.camera.grab(timeout_s)


@pytest.fixture
def unplugged(simulated):
    """Wraps the simulated camera: ``unplugged(fail_at, away)`` is lost at that grab."""
    return lambda fail_at, away=0: Unplugged(simulated.camera, fail_at, away)
