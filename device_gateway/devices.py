"""The small interfaces every driver implements: camera, thermal camera, projector.

A driver is the gateway's handle on one physical (or simulated) device; the device's calibration is
a :class:`services.geometry.camera.CameraModel` in the rig, a separate concept with its own name.

A driver is opened once and then used for many captures. ``open`` fails fast with
:class:`DeviceUnavailable` when the hardware (or display) is not there; a device
that stops answering during a capture raises :class:`DeviceLost`, after which the
station closes and re-opens it.
"""

from __future__ import annotations

import abc
import ipaddress
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.geometry.camera_model import DeviceKind


class DeviceError(RuntimeError):
    """A device problem, as opposed to bad input or a bug."""


class DeviceUnavailable(DeviceError):
    """The device cannot be opened (not connected, no display, refused); the message says which and why."""


class DeviceLost(DeviceError):
    """The device stopped answering during a capture; that capture is failed and the device re-opened."""


@dataclass(frozen=True)
class DeviceInfo:
    """What the gateway reports about one device."""

    name: str
    kind: DeviceKind
    driver: str
    width: int
    height: int
    model: str = ""
    serial: str = ""


@dataclass(frozen=True)
class Frame:
    """One image grabbed from a device.

    ``image`` is uint8/uint16 grey for a camera and float32 degrees Celsius for a
    thermal camera; ``timestamp`` is the host's wall-clock time (seconds since the
    epoch) when the frame was exposed, or received when the device gives no better.
    """

    image: np.ndarray
    timestamp: float
    metadata: dict[str, Any] = field(default_factory=dict)


class DeviceDriver(abc.ABC):
    """A device the gateway owns: opened once, closed on shutdown, re-opened after a loss."""

    @property
    @abc.abstractmethod
    def info(self) -> DeviceInfo:
        """Name, kind, driver, resolution and identity of the device."""

    @abc.abstractmethod
    def open(self) -> None:
        """Connect to the device; raise :class:`DeviceUnavailable` quickly when it is not there."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the device; safe to call when it is not open."""

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """Whether ``open`` succeeded and the device has not been closed or lost since."""


class CameraDriver(DeviceDriver):
    """A visible camera filming the projected patterns.

    Cameras that can change their exposure between frames (for automatic exposure and HDR of glowing
    parts) override ``exposure_us`` and ``set_exposure``; ``saturation_level`` is the grey level at
    which their sensor clips.
    """

    @abc.abstractmethod
    def grab(self, timeout_s: float) -> Frame:
        """A frame exposed after this call started; :class:`DeviceLost` when none comes in time."""

    @property
    def exposure_us(self) -> float | None:
        """The current exposure time in microseconds; None when the camera does not say."""
        return None

    def set_exposure(self, exposure_us: float) -> None:
        """Expose the following frames for ``exposure_us`` microseconds (manual exposure)."""
        raise DeviceUnavailable(f"camera {self.info.name!r} cannot change its exposure")

    @property
    def saturation_level(self) -> int:
        """Grey level at which the sensor saturates (255 for an 8-bit camera)."""
        return 255

    def prepare(self, patterns: np.ndarray) -> None:
        """Get ready to film ``patterns`` (F, H, W), the sequence every capture projects, once the camera is
        open. A real camera needs nothing; the simulated one renders their noiseless images."""


class ThermalDriver(DeviceDriver):
    """An infrared camera giving temperatures in degrees Celsius."""

    @abc.abstractmethod
    def grab(self, timeout_s: float) -> Frame:
        """A float32 temperature frame; :class:`DeviceLost` when none comes in time."""


class ProjectorDriver(DeviceDriver):
    """A projector showing full-screen patterns."""

    @property
    @abc.abstractmethod
    def settle_s(self) -> float:
        """Seconds from ``show`` until the pattern is steadily on the part (display latency)."""

    @abc.abstractmethod
    def show(self, pattern: np.ndarray) -> None:
        """Put a (height, width) uint8 pattern on the projector."""


def is_ip_address(text: str) -> bool:
    """Whether a device id is an IP address (a network camera opened directly, without a discovery search)."""
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True
