"""GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8, the GenICam reference stack on Linux, from
Python through PyGObject.

A camera is opened by its Aravis device id (as ``arv-tool-0.8`` lists it, e.g. ``Aravis-Fake-GV01``) or by
the IP address of a GigE Vision camera. An id is looked up by one discovery on every network interface (a
broadcast) and on USB; an IP address is connected to directly, which is what a container network passes (as
for the OAK driver) and what the tests use on loopback. Ids beginning with ``Fake_`` are Aravis' in-process
fake cameras (its ``Fake`` interface, for tests and demonstrations).

Each frame of a pattern sequence is triggered: ``trigger="Software"`` fires the GenICam ``TriggerSoftware``
command when the station grabs (the tests; a station without sync wiring), ``trigger="Line1"`` (or any
``LineN``) waits for the frame a pulse on that input line triggered (production: the projector's sync out
wired to the camera's opto-isolated input, docs/devices.md). ``trigger=None`` lets the camera run free (a
thermal camera streaming at its own rate). Whatever the trigger, a grab returns the first frame exposed after
it started: frames queued before it are dropped.

Timestamps come from the camera: each GVSP/U3V leader carries the camera's clock at exposure. They are put on
the host's wall clock with the offset (host receipt time minus camera time) of the first frame of each capture
(grabs more than a second after the last one), so that a sequence's frame intervals are the camera's exactly
and the absolute time is late by that frame's transfer (milliseconds); taking it afresh each capture keeps the
clocks' drift (parts per million) from adding up.

A frame that arrives incomplete (lost packets), a camera that stops answering its control channel (unplugged,
powered off, killed) and a trigger that brings no frame in time are :class:`DeviceLost` naming the camera;
the driver closes it and the station re-opens it for the next capture.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import Any

import gi
import numpy as np

gi.require_version("Aravis", "0.8")
from gi.repository import Aravis, GLib  # noqa: E402  (after the version it must load is chosen)

from device_gateway.devices import (  # noqa: E402
    CameraDriver, DeviceInfo, DeviceLost, DeviceUnavailable, Frame, ThermalDriver, is_ip_address,
)

ZERO_CELSIUS_K = 273.15
_BUFFERS = 8  # stream buffers: a sequence's frames never wait for one, a hardware trigger's burst is absorbed
_RESYNC_PAUSE_S = 1.0  # grabs further apart than this start a new capture: the clock offset is taken afresh
# How long a GigE Vision frame waits for its last packets before it counts as incomplete (Aravis' default, 100 ms,
# is for video rates; a pattern's frame may wait longer for a host busy with the scan before it is a loss).
_FRAME_RETENTION_US = 1_000_000


@dataclass(frozen=True)
class PixelFormat:
    """A monochrome GenICam pixel format the driver reads: its name, numpy type and significant bits."""

    name: str
    dtype: type
    bits: int

    @property
    def saturation_level(self) -> int:
        return (1 << self.bits) - 1

    @property
    def code(self) -> int:
        """The GenICam Pixel Format Naming Convention's code of the format (Aravis' ``PIXEL_FORMAT_MONO_*``)."""
        return getattr(Aravis, f"PIXEL_FORMAT_MONO_{self.bits}")


# Unpacked monochrome formats only: each pixel a little-endian 8- or 16-bit word, kept at its full depth.
PIXEL_FORMATS = {f"Mono{bits}": PixelFormat(f"Mono{bits}", np.uint8 if bits == 8 else np.uint16, bits)
                 for bits in (8, 10, 12, 14, 16)}


def counts_to_celsius(counts: np.ndarray, kelvin_per_count: float, offset_k: float = 0.0) -> np.ndarray:
    """Temperatures in degrees Celsius of a radiometric thermal camera's counts.

    Parameters
    ----------
    counts : (h, w) integer array
        The camera's temperature-linear output, e.g. Mono16.
    kelvin_per_count : float
        The stated resolution of that output, e.g. 0.01 or 0.1 K per count.
    offset_k : float
        Kelvin at count 0 (0 for the usual temperature-linear modes).

    Returns
    -------
    (h, w) float32 array of degrees Celsius.

    Notes
    -----
    :math:`T_{°C} = c \\cdot s + o - 273.15` with count :math:`c`, scale :math:`s` (K per count) and
    offset :math:`o` (K).
    """
    if not kelvin_per_count > 0:
        raise ValueError(f"A thermal camera's scale must be a positive number of kelvin per count; "
                         f"got {kelvin_per_count}.")
    counts = np.asarray(counts)
    if counts.dtype.kind not in "ui":
        raise ValueError(f"Radiometric counts must be integers; got {counts.dtype}.")
    return (counts * np.float64(kelvin_per_count) + (offset_k - ZERO_CELSIUS_K)).astype(np.float32)


class CameraClock:
    """Maps a camera's timestamps (nanoseconds of its own clock) to the host's wall clock.

    The offset between the clocks is taken from the first frame observed (host receipt time - camera time, late
    by that frame's transfer) and held until :meth:`forget`: the frames mapped meanwhile keep the camera's own
    intervals exactly.
    """

    def __init__(self) -> None:
        self.offset_ns: int | None = None

    def observe(self, camera_ns: int, host_ns: int) -> None:
        if self.offset_ns is None:
            self.offset_ns = host_ns - camera_ns

    def forget(self) -> None:
        """Take the offset afresh from the next frame (the clocks drift apart by parts per million)."""
        self.offset_ns = None

    def wall_time(self, camera_ns: int) -> float:
        """Seconds since the epoch on the host's clock of the camera's ``camera_ns``."""
        if self.offset_ns is None:
            raise ValueError("The camera clock has no offset yet: observe a frame first.")
        return (camera_ns + self.offset_ns) / 1e9


def _found_devices() -> list[str]:
    Aravis.update_device_list()
    return [Aravis.get_device_id(index) for index in range(Aravis.get_n_devices())]


def _trigger_name(trigger: str | None) -> str:
    return "free-running" if trigger is None else f"{trigger} trigger"


class _GenicamDevice:
    """Connection, configuration and stream shared by the GenICam camera and thermal camera."""

    role: str

    def __init__(self, name: str, device_id: str, pixel_format: str, trigger: str | None,
                 exposure_us: float | None, gain: float | None,
                 region: tuple[int, int, int, int] | None) -> None:
        if not device_id:
            raise ValueError(f"The GenICam {self.role} {name!r} needs its Aravis device id or IP address.")
        if pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"GenICam pixel format {pixel_format!r} is not read by the driver; use one of "
                             f"{', '.join(PIXEL_FORMATS)}.")
        if trigger is not None and trigger != "Software" and not (trigger.startswith("Line")
                                                                 and trigger[4:].isdigit()):
            raise ValueError(f"A GenICam trigger is 'Software' or an input line such as 'Line1'; got {trigger!r}.")
        if exposure_us is not None and not exposure_us > 0:
            raise ValueError(f"The exposure must be a positive number of microseconds; got {exposure_us}.")
        if region is not None and (len(region) != 4 or min(region) < 0 or min(region[2:]) < 1):
            raise ValueError(f"A region is (offset x, offset y, width, height) with a positive size; got {region}.")
        self.name = name
        self.device_id = device_id
        self.format = PIXEL_FORMATS[pixel_format]
        self.trigger = trigger
        self._exposure_us = exposure_us
        self.gain = gain
        self.region = region
        self._camera: Any = None
        self._stream: Any = None
        self._lost_handler: int | None = None
        self._control_lost = threading.Event()
        self._clock = CameraClock()
        self._frames = 0  # delivered since opened: a loss says how far it got
        self._last_grab_s = -np.inf
        self._size = (region[2], region[3]) if region is not None else (0, 0)
        self._model = self._serial = ""

    @property
    def label(self) -> str:
        """How messages name the device: its role, name and Aravis id."""
        return f"{self.role} {self.name!r} (GenICam {self.device_id})"

    @property
    def info(self) -> DeviceInfo:
        return DeviceInfo(self.name, self.role, "genicam", self._size[0], self._size[1], self._model, self._serial)

    @property
    def is_open(self) -> bool:
        return self._stream is not None and not self._control_lost.is_set()

    def open(self) -> None:
        self.close()
        self._camera = self._connect()
        try:
            self._configure(self._camera)
            stream = self._camera.create_stream(None, None)
            if isinstance(stream, Aravis.GvStream):  # a socket buffer of a whole frame, and time for its packets
                stream.set_property("socket-buffer", Aravis.GvStreamSocketBuffer.AUTO)
                stream.set_property("frame-retention", _FRAME_RETENTION_US)
            payload = self._camera.get_payload()
            for _ in range(_BUFFERS):
                stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            self._control_lost.clear()
            self._lost_handler = self._camera.get_device().connect("control-lost",
                                                                   lambda _device: self._control_lost.set())
            self._stream, self._clock, self._frames = stream, CameraClock(), 0
            self._camera.start_acquisition()
        except (GLib.Error, DeviceUnavailable) as error:
            failure = error if isinstance(error, DeviceUnavailable) else DeviceUnavailable(
                f"{self.label}: cannot start it: {error.message}")
            stream = None
            self.close()
            # The traceback would keep the camera alive through its frames, and with it the control channel.
            raise failure.with_traceback(None) from None

    def _connect(self) -> Any:
        if self.device_id.startswith("Fake_"):  # Aravis' in-process fake camera, opened first among interfaces
            Aravis.enable_interface("Fake")
        elif not is_ip_address(self.device_id):
            found = _found_devices()
            if self.device_id not in found:
                raise DeviceUnavailable(f"{self.label} is not connected (found: {', '.join(found) or 'none'})")
        try:
            return Aravis.Camera.new(self.device_id)
        except GLib.Error as error:
            raise DeviceUnavailable(f"{self.label}: cannot connect: {error.message}") from None

    def _configure(self, camera: Any) -> None:
        offered = camera.dup_available_pixel_formats_as_strings()
        if self.format.name not in offered:
            raise DeviceUnavailable(f"{self.label} does not offer pixel format {self.format.name} "
                                    f"(it offers {', '.join(offered)})")
        camera.set_pixel_format_from_string(self.format.name)
        if self.region is not None:
            sensor = camera.get_sensor_size()
            x, y, width, height = self.region
            if x + width > sensor.width or y + height > sensor.height:
                raise DeviceUnavailable(f"{self.label}: region {width}x{height} at ({x}, {y}) does not fit its "
                                        f"{sensor.width}x{sensor.height} sensor")
            camera.set_region(x, y, width, height)
        if self._exposure_us is not None:
            camera.set_exposure_time(self._exposure_us)
        if self.gain is not None:
            camera.set_gain(self.gain)
        camera.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
        if self.trigger is None:
            camera.clear_triggers()
        else:
            camera.set_trigger(self.trigger)
        region = camera.get_region()
        if self.region is not None and (region.width, region.height) != self.region[2:]:
            raise DeviceUnavailable(f"{self.label} set its region to {region.width}x{region.height}, not the "
                                    f"{self.region[2]}x{self.region[3]} configured (its width or height step?)")
        self._size = (region.width, region.height)
        self._model = f"{camera.get_vendor_name()} {camera.get_model_name()}".strip()
        self._serial = camera.get_device_serial_number() or ""
        self._exposure_us = camera.get_exposure_time() if camera.is_exposure_time_available() else None

    def close(self) -> None:
        camera, stream, self._camera, self._stream = self._camera, self._stream, None, None
        if camera is None:
            return
        if stream is not None:
            try:
                camera.stop_acquisition()
            except GLib.Error:
                pass  # already gone: closing a lost camera must not fail
        if self._lost_handler is not None:
            camera.get_device().disconnect(self._lost_handler)
            self._lost_handler = None
        # Dropping the last references stops the stream's thread and releases the camera's control channel.
        del stream, camera

    def _lose(self, problem: str) -> DeviceLost:
        self.close()
        return DeviceLost(f"{self.label}: {problem} (after {self._frames} frames since it was opened)")

    def _next_buffer(self, timeout_s: float) -> Any:
        """The first complete frame exposed after this call (an Aravis buffer, to be pushed back once read)."""
        if self._stream is None:
            raise DeviceLost(f"{self.label} is not open")
        if self._control_lost.is_set():
            raise self._lose("its control channel was lost (unplugged or powered off?)")
        requested_ns = time.time_ns()
        if time.monotonic() - self._last_grab_s > _RESYNC_PAUSE_S:
            self._clock.forget()
        while (stale := self._stream.try_pop_buffer()) is not None:  # queued frames were exposed before
            if stale.get_status() == Aravis.BufferStatus.SUCCESS:
                self._observe(stale)
            self._stream.push_buffer(stale)
        if self.trigger == "Software":
            try:
                self._camera.software_trigger()
            except GLib.Error as error:
                raise self._lose(f"cannot trigger it: {error.message}") from None
        deadline = time.monotonic() + timeout_s
        # The first software trigger after the stream starts can come before the camera's acquisition runs (seen
        # with arv-fake-gv-camera: no frame, "after 0 frames"); it is fired once more halfway through the wait.
        retrigger_at = time.monotonic() + timeout_s / 2 if self.trigger == "Software" and self._frames == 0 else None
        while (remaining := deadline - time.monotonic()) > 0:
            wait = remaining if retrigger_at is None else max(0.0, min(remaining, retrigger_at - time.monotonic()))
            buffer = self._stream.timeout_pop_buffer(max(1, int(wait * 1e6)))
            if buffer is None:
                if retrigger_at is not None:
                    retrigger_at = None
                    try:
                        self._camera.software_trigger()
                    except GLib.Error as error:
                        raise self._lose(f"cannot trigger it: {error.message}") from None
                    continue
                break
            status = buffer.get_status()
            if status == Aravis.BufferStatus.CLEARED:
                # Returned unfilled: Aravis hands a buffer back for a stray packet that starts no frame (a late
                # one, or a packet-size test packet), as seen with arv-fake-gv-camera on a busy host.
                self._stream.push_buffer(buffer)
                continue
            if status != Aravis.BufferStatus.SUCCESS:
                frame_id, missing = buffer.get_frame_id(), self._missing_packets()
                raise self._lose(f"frame {frame_id} arrived incomplete ({status.value_nick}; {missing} packets "
                                 "lost since it was opened)")
            self._observe(buffer)
            if self.trigger == "Software" or self._clock.wall_time(buffer.get_timestamp()) * 1e9 >= requested_ns:
                return buffer
            self._stream.push_buffer(buffer)  # exposed before the call (in flight when it started)
        if self._control_lost.is_set():
            raise self._lose("its control channel was lost (unplugged or powered off?)")
        raise self._lose(f"no frame within {timeout_s:g} s ({_trigger_name(self.trigger)})")

    def _observe(self, buffer: Any) -> None:
        self._clock.observe(buffer.get_timestamp(), buffer.get_system_timestamp())

    def _missing_packets(self) -> int:
        try:
            return int(self._stream.get_statistics()[1])
        except (AttributeError, TypeError, IndexError):
            return 0

    def _image(self, buffer: Any) -> np.ndarray:
        """The buffer's pixels at the format's full depth, as a (height, width) array of its own."""
        width, height = buffer.get_image_width(), buffer.get_image_height()
        code = buffer.get_image_pixel_format()
        if code != self.format.code:
            raise self._lose(f"sent pixel format 0x{code:08x}, not the {self.format.name} configured")
        data = buffer.get_image_data()
        dtype = np.dtype(self.format.dtype).newbyteorder("<")
        if len(data) < width * height * dtype.itemsize:
            raise self._lose(f"sent {len(data)} bytes for a {width}x{height} {self.format.name} frame")
        return np.frombuffer(data, dtype, count=width * height).reshape(height, width).astype(self.format.dtype)

    def _grab(self, timeout_s: float) -> tuple[np.ndarray, float, dict[str, Any]]:
        buffer = self._next_buffer(timeout_s)
        try:
            image = self._image(buffer)
            camera_ns = buffer.get_timestamp()
            metadata = {"driver": "genicam", "frame_id": int(buffer.get_frame_id()),
                        "camera_timestamp_ns": int(camera_ns), "pixel_format": self.format.name}
            if self._exposure_us is not None:
                metadata["exposure_us"] = round(float(self._exposure_us), 3)
            self._frames += 1
            self._last_grab_s = time.monotonic()
            return image, self._clock.wall_time(camera_ns), metadata
        finally:
            if self._stream is not None:  # not when the frame was refused: the stream is gone with the camera
                self._stream.push_buffer(buffer)


class GenicamCamera(_GenicamDevice, CameraDriver):
    """A GenICam camera filming the patterns: monochrome frames at the pixel format's full depth (uint8 for
    Mono8, uint16 for Mono10..Mono16), manual exposure and gain, a region of the sensor, one triggered frame
    per grab.

    Parameters
    ----------
    name : str
        The device's name in the rig.
    device_id : str
        Aravis device id, or the IP address of a GigE Vision camera.
    pixel_format : str
        Mono8, Mono10, Mono12, Mono14 or Mono16 (unpacked).
    exposure_us : float, optional
        Manual exposure; None keeps the camera's.
    gain : float, optional
        The camera's ``Gain`` (dB on most cameras; ``GainRaw`` on older ones); None keeps the camera's.
    region : (x, y, width, height), optional
        The part of the sensor to read; None keeps the camera's.
    trigger : str
        ``Software`` or an input line, e.g. ``Line1``.
    """

    role = "camera"

    def __init__(self, name: str = "camera", device_id: str = "", pixel_format: str = "Mono8",
                 exposure_us: float | None = 8000.0, gain: float | None = None,
                 region: tuple[int, int, int, int] | None = None, trigger: str = "Software") -> None:
        super().__init__(name, device_id, pixel_format, trigger, exposure_us, gain, region)

    @property
    def exposure_us(self) -> float | None:
        return self._exposure_us

    def set_exposure(self, exposure_us: float) -> None:
        if not exposure_us > 0:
            raise ValueError(f"The exposure must be a positive number of microseconds; got {exposure_us}.")
        if self._camera is None:
            self._exposure_us = float(exposure_us)
            return
        try:
            self._camera.set_exposure_time(float(exposure_us))
            self._exposure_us = self._camera.get_exposure_time()
        except GLib.Error as error:
            raise self._lose(f"cannot set the exposure: {error.message}") from None

    @property
    def saturation_level(self) -> int:
        return self.format.saturation_level

    def grab(self, timeout_s: float) -> Frame:
        image, timestamp, metadata = self._grab(timeout_s)
        return Frame(image, timestamp, metadata)


class GenicamThermal(_GenicamDevice, ThermalDriver):
    """A radiometric thermal camera on GenICam: temperature-linear counts (Mono16 by default) at a stated
    ``kelvin_per_count`` and ``offset_k``, turned into float32 degrees Celsius.

    It runs free by default (``trigger=None``): a grab returns the first frame exposed after it started.
    """

    role = "thermal"

    def __init__(self, name: str = "thermal", device_id: str = "", pixel_format: str = "Mono16",
                 kelvin_per_count: float = 0.01, offset_k: float = 0.0, trigger: str | None = None,
                 region: tuple[int, int, int, int] | None = None) -> None:
        counts_to_celsius(np.zeros(1, np.uint16), kelvin_per_count, offset_k)  # refuse a bad scale before opening
        super().__init__(name, device_id, pixel_format, trigger, None, None, region)
        self.kelvin_per_count, self.offset_k = kelvin_per_count, offset_k

    def grab(self, timeout_s: float) -> Frame:
        counts, timestamp, metadata = self._grab(timeout_s)
        metadata.update(units="degC", kelvin_per_count=self.kelvin_per_count, offset_k=self.offset_k)
        return Frame(counts_to_celsius(counts, self.kelvin_per_count, self.offset_k), timestamp, metadata)
