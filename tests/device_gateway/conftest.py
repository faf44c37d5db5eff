"""A quarter-resolution forging station, so that tracing the simulated view takes a fraction of a second."""

from __future__ import annotations

import numpy as np
import pytest

from device_gateway.drivers.simulated import SimulatedStation
from device_gateway.station import Station
from services.formats.rig import Device, Rig
from services.simulation import presets
from services.structured_light.patterns import generate_sequence

SCALE = 4


def _downscaled(device: Device, scale: int) -> Device:
    K = device.K_array.copy()
    K[:2, :2] /= scale
    K[:2, 2] = (K[:2, 2] + 0.5) / scale - 0.5  # pixel centres at integers
    return device.model_copy(update={"width": device.width // scale, "height": device.height // scale,
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
