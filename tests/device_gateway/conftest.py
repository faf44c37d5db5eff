"""A quarter-resolution forging station (tracing its view takes a fraction of a second), device faults, and
Aravis' fake GenICam cameras."""

from __future__ import annotations

import fcntl
import shutil
import socket
import subprocess
import tempfile
import time
from pathlib import Path

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


def _aravis_fake_ramp(width: int, height: int, frame_id: int, exposure_us: float, gain: int, bits: int) -> np.ndarray:
    """Aravis' fake camera image of frame ``frame_id`` (``arv_fake_camera_diagonal_ramp`` in Aravis 0.8):
    pixel (x, y) is ``((x + y + id) % 255) * scale`` in Mono8 and ``((256 * (x + y + id)) % 65535) * scale`` in
    Mono16, clipped to the format's range and truncated, with ``scale = 1 + GainRaw + log10(ExposureTimeAbs /
    10000 us)``; x and y count from the region's corner."""
    y, x = np.mgrid[:height, :width]
    scale = 1.0 + gain + np.log10(int(exposure_us) / 10000.0)
    if bits == 8:
        return np.clip(((x + y + frame_id) % 255) * scale, 0, 255).astype(np.uint8)
    return np.clip(((256 * (x + y + frame_id)) % 65535) * scale, 0, 65535).astype(np.uint16)


@pytest.fixture
def aravis_fake_ramp():
    """The fake cameras' images as ground truth: ``aravis_fake_ramp(width, height, frame_id, exposure_us, gain,
    bits)``, so a frame shows the exposure, gain and region the driver set and which frame of the camera it is."""
    return _aravis_fake_ramp


GV_FAKE_ADDRESS = "127.0.0.1"  # its GigE Vision control port, 3956, is fixed: one fake camera at a time
# ... across the test processes too (make test runs two): a camera holds this file's lock from start to close
GV_FAKE_LOCK = Path(tempfile.gettempdir()) / "thermofield-fake-gv-camera.lock"


def _answers_discovery(address: str, timeout_s: float) -> bool:
    """Whether a GigE Vision device at ``address`` acknowledges a unicast GVCP discovery (no broadcast)."""
    # The 8-byte GVCP header of DISCOVERY_CMD (GigE Vision 2.0, 15.1): key 0x42, flags ack-required, command 2.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.settimeout(timeout_s)
        probe.sendto(bytes([0x42, 0x01, 0x00, 0x02, 0x00, 0x00, 0x00, 0x01]), (address, 3956))
        try:
            answer = probe.recv(1024)
        except (TimeoutError, ConnectionRefusedError):
            return False
    return answer[2:4] == b"\x00\x03"  # DISCOVERY_ACK


class FakeGigEVisionCamera:
    """``arv-fake-gv-camera-0.8`` serving on loopback: a real GigE Vision peer (GVCP control, GVSP stream),
    Aravis' diagonal ramp as its images. ``kill`` takes it away as an unplugged camera; ``start`` brings it back."""

    def __init__(self, address: str = GV_FAKE_ADDRESS, lost_per_thousand: int = 0) -> None:
        self.address, self.lost_per_thousand = address, lost_per_thousand
        self.process: subprocess.Popen | None = None
        self._lock = None

    def start(self) -> FakeGigEVisionCamera:
        executable = shutil.which("arv-fake-gv-camera-0.8")
        assert executable, "arv-fake-gv-camera-0.8 is missing: make system-libraries installs aravis-tools"
        if self._lock is None:  # the port is this camera's until close(), across kill() and start()
            self._lock = open(GV_FAKE_LOCK, "w")
            fcntl.flock(self._lock, fcntl.LOCK_EX)
        assert not _answers_discovery(self.address, 0.2), f"a GigE Vision device already answers at {self.address}"
        arguments = [executable, "-i", self.address, "-s", "GV01"]
        if self.lost_per_thousand:
            arguments += ["-r", str(self.lost_per_thousand)]
        self.process = subprocess.Popen(arguments, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 10
        while not _answers_discovery(self.address, 0.2):
            assert self.process.poll() is None, f"arv-fake-gv-camera-0.8 exited: {self.process.stderr.read()}"
            assert time.monotonic() < deadline, "arv-fake-gv-camera-0.8 did not answer discovery"
        return self

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(timeout=10)

    def close(self) -> None:
        """Kill it and give the port to the next camera."""
        self.kill()
        if self._lock is not None:
            self._lock.close()  # releases the lock
            self._lock = None


@pytest.fixture
def fake_gv_camera():
    """A fresh ``arv-fake-gv-camera-0.8 -i 127.0.0.1`` (id ``Aravis-Fake-GV01``), stopped after the test."""
    camera = FakeGigEVisionCamera().start()
    yield camera
    camera.close()


@pytest.fixture
def lossy_gv_camera():
    """The fake GigE Vision camera dropping 300 of every 1000 stream packets."""
    camera = FakeGigEVisionCamera(lost_per_thousand=300).start()
    yield camera
    camera.close()
