"""Luxonis OAK cameras through depthai's v3 API: a ``Camera`` node with manual exposure and focus, the OAK-T
``Thermal`` node with an explicit ``ThermalConfig``.

A device configured by IP address is connected to directly (``dai.DeviceInfo(ip)``): the
Ethernet-only OAK-T is otherwise found by a broadcast search, which a container network
does not pass. Other devices are found by one search (``Device.getAllAvailableDevices``,
about half a second) and only the one asked for is connected, so a missing device is
reported at once by name instead of blocking in depthai's implicit search.
"""

from __future__ import annotations

import abc
import datetime
import time
from typing import Any, Literal

import depthai as dai
import numpy as np

from device_gateway.devices import (CameraDriver, DeviceInfo, DeviceLost, DeviceUnavailable, Frame, ThermalDriver,
                                    is_ip_address)


def find_device(device_id: str | None, role: str) -> dai.DeviceInfo:
    """The connected OAK with ``device_id`` (serial/MxId, IP address or name), or the only one when None or empty.

    Raises
    ------
    DeviceUnavailable
        When no device, not that device, or several devices (and no id) are found.
    """
    if device_id and is_ip_address(device_id):
        return dai.DeviceInfo(device_id)
    found = dai.Device.getAllAvailableDevices()
    described = ", ".join(f"{info.getDeviceId()} ({info.name})" for info in found) or "none"
    if device_id:
        for info in found:
            if device_id in (info.getDeviceId(), info.name):
                return info
        raise DeviceUnavailable(f"{role}: OAK device {device_id!r} is not connected (found: {described})")
    if len(found) != 1:
        problem = "no OAK device is connected" if not found else f"several OAK devices are connected ({described})"
        raise DeviceUnavailable(f"{role}: {problem}; set its device id in the gateway configuration")
    return found[0]


def configure_camera(control: dai.CameraControl, exposure_us: int, iso: int, lens_position: int) -> None:
    """Fix exposure and focus on ``control`` (a ``Camera`` node's ``initialControl``).

    Auto-exposure would fight the black and white patterns; autofocus would move the lens
    and with it the calibrated focal length and distortion, so the lens stays at the
    configured position, the one the camera was calibrated at (fixed-focus OAKs ignore it).
    """
    if not 0 <= lens_position <= 255:
        raise ValueError(f"The OAK lens position must be 0..255 (depthai's manual focus); got {lens_position}.")
    control.setManualExposure(exposure_us, iso)
    control.setManualFocus(lens_position)


def configure_thermal(config: dai.ThermalConfig, gain_mode: Literal["low", "high"]) -> None:
    """Set the OAK-T's measurement parameters on ``config`` (a ``Thermal`` node's ``initialConfig``).

    The gain mode is set explicitly: low gain measures up to 900 K, high gain up to 500 K
    with less noise (depthai's ``ThermalAmbientParams``). The sensor's own emissivity
    correction is neutralised (target emissivity 128/128 = 1): thermofield corrects
    emissivity itself (services/fusion/radiometry.py), and applying it twice would
    overstate every temperature.
    """
    modes = {"low": dai.ThermalGainMode.LOW, "high": dai.ThermalGainMode.HIGH}
    if gain_mode not in modes:
        raise ValueError(f"The OAK-T gain mode must be 'low' or 'high'; got {gain_mode!r}.")
    config.ambientParams.gainMode = modes[gain_mode]
    config.ambientParams.targetEmissivity = 128


def host_time_of(message: dai.ImgFrame) -> float:
    """Wall-clock seconds since the epoch at which a frame was exposed.

    depthai stamps frames on the host's steady clock (``dai.Clock``); the offset to
    the wall clock is measured now.
    """
    age = (dai.Clock.now() - message.getTimestamp()).total_seconds()
    return time.time() - age


def frame_metadata(message: dai.ImgFrame) -> dict[str, Any]:
    """Sequence number, exposure settings and lens position a frame reports."""
    return {
        "sequence": int(message.getSequenceNum()),
        "exposure_us": round(message.getExposureTime().total_seconds() * 1e6),
        "iso": int(message.getSensitivity()),
        "lens_position": int(message.getLensPosition()),
    }


class _OakDevice(abc.ABC):
    """Connection, pipeline and output queue shared by the OAK drivers."""

    role: str

    def __init__(self, name: str, device_id: str | None, socket: str, width: int, height: int) -> None:
        if not hasattr(dai.CameraBoardSocket, socket):
            raise ValueError(f"Unknown OAK board socket {socket!r}; use e.g. CAM_A, CAM_B, CAM_C or CAM_E.")
        self.name = name
        self.device_id = device_id
        self.socket = getattr(dai.CameraBoardSocket, socket)
        self.width, self.height = width, height
        self._device: dai.Device | None = None
        self._pipeline: dai.Pipeline | None = None
        self._queue: dai.MessageQueue | None = None
        self._serial = ""
        self._model = ""

    @abc.abstractmethod
    def _build(self, pipeline: dai.Pipeline) -> dai.Node.Output:
        """Create the device's node in ``pipeline`` and return the output to read frames from."""

    @property
    def info(self) -> DeviceInfo:
        return DeviceInfo(self.name, self.role, "oak", self.width, self.height, self._model, self._serial)

    @property
    def is_open(self) -> bool:
        return self._queue is not None and self._device is not None and not self._device.isClosed()

    def open(self) -> None:
        found = find_device(self.device_id, f"{self.role} {self.name!r}")
        try:
            self._device = dai.Device(found)
            self._serial = found.getDeviceId()
            self._model = self._device.getDeviceName()
            self._pipeline = dai.Pipeline(self._device)
            output = self._build(self._pipeline)
            self._queue = output.createOutputQueue(maxSize=4, blocking=False)
            self._pipeline.start()
        except RuntimeError as error:
            self.close()
            raise DeviceUnavailable(
                f"{self.role} {self.name!r}: cannot start OAK {found.getDeviceId()}: {error}"
            ) from None

    def close(self) -> None:
        releases = [self._pipeline.stop] if self._pipeline is not None else []
        releases += [self._device.close] if self._device is not None else []
        for release in releases:
            try:
                release()
            except RuntimeError:
                pass  # already gone: closing a lost device must not fail
        self._device = self._pipeline = self._queue = None

    def _next_message(self, timeout_s: float) -> dai.ImgFrame:
        """The first frame exposed after this call (older queued frames are dropped)."""
        if self._queue is None:
            raise DeviceLost(f"{self.role} {self.name!r} is not open")
        requested = dai.Clock.now()
        deadline = time.monotonic() + timeout_s
        try:
            self._queue.tryGetAll()
            while (remaining := deadline - time.monotonic()) > 0:
                message = self._queue.get(datetime.timedelta(seconds=remaining))
                if message is not None and message.getTimestamp() >= requested:
                    return message
        except (RuntimeError, dai.MessageQueue.QueueException) as error:
            self.close()
            raise DeviceLost(f"{self.role} {self.name!r}: connection lost: {error}") from None
        self.close()
        raise DeviceLost(f"{self.role} {self.name!r}: no frame within {timeout_s:g} s")


class OakCamera(_OakDevice, CameraDriver):
    """An OAK colour/mono sensor as a grey 8-bit camera with manual exposure, settable between frames.

    ``set_exposure`` sends a ``CameraControl`` with ``setManualExposure`` through the Camera node's
    ``inputControl`` queue (depthai v3: ``Node.Input.createInputQueue``); frames report the exposure they
    were taken with (``exposure_us`` in their metadata), and the station meters with those frames.
    """

    role = "camera"

    def __init__(self, name: str = "camera", device_id: str | None = None, socket: str = "CAM_A",
                 width: int = 1280, height: int = 800, exposure_us: int = 8000, iso: int = 100,
                 lens_position: int = 130) -> None:
        super().__init__(name, device_id, socket, width, height)
        configure_camera(dai.CameraControl(), exposure_us, iso, lens_position)  # refuse bad values before opening
        self._exposure_us, self.iso, self.lens_position = exposure_us, iso, lens_position
        self._control: dai.InputQueue | None = None

    @property
    def exposure_us(self) -> int:
        return self._exposure_us

    def set_exposure(self, exposure_us: float) -> None:
        if not exposure_us > 0:
            raise ValueError(f"The exposure must be a positive number of microseconds; got {exposure_us}.")
        self._exposure_us = max(1, round(exposure_us))
        if self._control is not None:
            control = dai.CameraControl()
            control.setManualExposure(self._exposure_us, self.iso)
            try:
                self._control.send(control)
            except RuntimeError as error:
                self.close()
                raise DeviceLost(f"{self.role} {self.name!r}: cannot set the exposure: {error}") from None

    def close(self) -> None:
        self._control = None
        super().close()

    def _build(self, pipeline: dai.Pipeline) -> dai.Node.Output:
        node = pipeline.create(dai.node.Camera).build(self.socket)
        configure_camera(node.initialControl, self._exposure_us, self.iso, self.lens_position)
        self._control = node.inputControl.createInputQueue()
        return node.requestOutput((self.width, self.height), dai.ImgFrame.Type.GRAY8)

    def grab(self, timeout_s: float) -> Frame:
        message = self._next_message(timeout_s)
        return Frame(np.array(message.getFrame(), dtype=np.uint8), host_time_of(message), frame_metadata(message))


class OakThermal(_OakDevice, ThermalDriver):
    """The OAK-T radiometric sensor: its ``temperature`` output (FP16 degrees Celsius) as float32."""

    role = "thermal"

    def __init__(self, name: str = "thermal", device_id: str | None = None, socket: str = "CAM_E",
                 width: int = 256, height: int = 192, fps: float = 25.0,
                 gain_mode: Literal["low", "high"] = "low") -> None:
        super().__init__(name, device_id, socket, width, height)
        configure_thermal(dai.ThermalConfig(), gain_mode)  # refuse a bad mode before opening
        self.fps, self.gain_mode = fps, gain_mode

    def _build(self, pipeline: dai.Pipeline) -> dai.Node.Output:
        node = pipeline.create(dai.node.Thermal).build(self.socket, self.fps)
        configure_thermal(node.initialConfig, self.gain_mode)
        return node.temperature

    def grab(self, timeout_s: float) -> Frame:
        message = self._next_message(timeout_s)
        metadata = {"sequence": int(message.getSequenceNum()), "units": "degC"}
        return Frame(thermal_image(message), host_time_of(message), metadata)


def thermal_image(message: dai.ImgFrame) -> np.ndarray:
    """The float32 temperature image (degrees Celsius) of a ``Thermal.temperature`` frame."""
    if message.getType() != dai.ImgFrame.Type.GRAYF16:
        raise DeviceLost(f"thermal frame has type {message.getType().name}, expected GRAYF16 temperatures")
    return np.asarray(message.getFrame(), dtype=np.float32)
