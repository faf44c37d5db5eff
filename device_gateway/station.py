"""A station: one camera, one thermal camera and one projector, captured together.

A capture shows each pattern, waits for the projector to settle, grabs the camera
frame, and after the last pattern grabs the thermal frame(s). Captures are
serialised (the devices can do one at a time). If a device is lost mid-capture the
capture fails with :class:`DeviceLost` and every device is closed and re-opened, so
the next capture starts clean.

Board views for calibration: the projector lights the scene white and, for each
view, the board holder puts the board in a new pose (a person, given
``interval_s`` seconds; the simulated rig, at once), then the camera and the
thermal camera grab one frame each.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from device_gateway.devices import Camera, Device, DeviceInfo, DeviceLost, DeviceUnavailable, Projector, ThermalCamera
from services.formats.board import BoardSpec
from services.formats.sequence import Sequence

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Capture:
    """What one capture returns.

    ``frames`` is (F, H, W) camera frames, one per frame of ``sequence`` in order;
    ``thermal`` is (T, h, w) float32 temperatures in degrees Celsius. Timestamps are
    wall-clock seconds since the epoch; metadata lists hold one dict per frame (a camera
    frame's ``file`` is its name in the manifest).
    """

    sequence: Sequence
    frames: np.ndarray
    frame_timestamps: np.ndarray
    frame_metadata: list[dict[str, Any]]
    thermal: np.ndarray
    thermal_timestamps: np.ndarray
    thermal_metadata: list[dict[str, Any]]
    devices: list[DeviceInfo]


@dataclass(frozen=True)
class BoardViews:
    """Paired views of a calibration board: ``camera`` (N, H, W) grey frames, ``thermal`` (N, h, w) float32
    degrees Celsius, wall-clock ``timestamps`` (N,) of the camera frames."""

    camera: np.ndarray
    thermal: np.ndarray
    timestamps: np.ndarray
    devices: list[DeviceInfo]


class BoardHolder(Protocol):
    """Who moves the calibration board between views."""

    def present(self, board: BoardSpec | None, view: int) -> None:
        """Hold ``board`` in the pose of view number ``view`` (returns when it is in place); None takes it away."""


class Station:
    """The devices of one station, owned by the gateway process.

    ``board_holder`` moves the board between calibration views; None means a person does, given
    ``interval_s`` seconds per view.
    """

    def __init__(self, camera: Camera, thermal: ThermalCamera, projector: Projector,
                 settle_s: float | None = None, grab_timeout_s: float = 2.0,
                 board_holder: BoardHolder | None = None) -> None:
        self.camera = camera
        self.thermal = thermal
        self.projector = projector
        self.board_holder = board_holder
        self.settle_s = projector.settle_s if settle_s is None else settle_s
        self.grab_timeout_s = grab_timeout_s
        self._lock = threading.Lock()

    @property
    def devices(self) -> list[Device]:
        return [self.camera, self.thermal, self.projector]

    def open(self) -> None:
        """Open every device that is not open yet; :class:`DeviceUnavailable` names the first that fails."""
        for device in self.devices:
            if not device.is_open:
                device.open()

    def close(self) -> None:
        for device in self.devices:
            device.close()

    def health(self) -> dict[str, bool]:
        """Whether each device (by name) is open and usable."""
        return {device.info.name: device.is_open for device in self.devices}

    def capture(self, sequence: Sequence, patterns: np.ndarray, thermal_frames: int = 1) -> Capture:
        """Project ``patterns`` one by one, film each, then grab ``thermal_frames`` thermal frames.

        Parameters
        ----------
        sequence : Sequence
            The manifest describing ``patterns``, returned with the frames.
        patterns : (F, H, W) uint8 array
            One image per manifest frame, at the projector's resolution.
        thermal_frames : int
            Thermal frames to grab after the last pattern.

        Raises
        ------
        ValueError
            When the patterns do not fit the projector or the manifest, or ``thermal_frames`` < 1.
        DeviceUnavailable
            When a device cannot be opened.
        DeviceLost
            When a device stops answering; the devices are re-opened before this is raised.
        """
        patterns = np.asarray(patterns)
        info = self.projector.info
        if patterns.ndim != 3 or patterns.shape[1:] != (info.height, info.width) or patterns.dtype != np.uint8:
            raise ValueError(
                f"Patterns must be a (F, {info.height}, {info.width}) uint8 stack for projector {info.name!r}; "
                f"got {patterns.shape} {patterns.dtype}."
            )
        if len(patterns) != len(sequence.frames):
            raise ValueError(
                f"The manifest lists {len(sequence.frames)} frames but {len(patterns)} patterns were given."
            )
        if thermal_frames < 1:
            raise ValueError(f"At least one thermal frame is needed; got {thermal_frames}.")
        with self._lock:
            self.open()
            try:
                return self._capture(sequence, patterns, thermal_frames)
            except DeviceLost:
                self._reopen()
                raise

    def _capture(self, sequence: Sequence, patterns: np.ndarray, thermal_frames: int) -> Capture:
        camera_frames = []
        for pattern in patterns:
            self.projector.show(pattern)
            if self.settle_s > 0:
                time.sleep(self.settle_s)
            camera_frames.append(self.camera.grab(self.grab_timeout_s))
        thermal = [self.thermal.grab(self.grab_timeout_s) for _ in range(thermal_frames)]
        return Capture(
            sequence=sequence,
            frames=np.stack([frame.image for frame in camera_frames]),
            frame_timestamps=np.array([frame.timestamp for frame in camera_frames]),
            frame_metadata=[{**frame.metadata, "file": entry.file}
                            for frame, entry in zip(camera_frames, sequence.frames)],
            thermal=np.stack([frame.image for frame in thermal]).astype(np.float32, copy=False),
            thermal_timestamps=np.array([frame.timestamp for frame in thermal]),
            thermal_metadata=[frame.metadata for frame in thermal],
            devices=[device.info for device in self.devices],
        )

    def board_views(self, board: BoardSpec, views: int, interval_s: float = 2.0) -> BoardViews:
        """Film a calibration board in ``views`` poses with the camera and the thermal camera together.

        Raises
        ------
        ValueError
            When ``views`` < 1 or ``interval_s`` < 0.
        DeviceUnavailable, DeviceLost
            As :meth:`capture`.
        """
        if views < 1 or interval_s < 0:
            raise ValueError(f"Board views need views >= 1 and interval_s >= 0; got {views} and {interval_s}.")
        info = self.projector.info
        with self._lock:
            self.open()
            try:
                self.projector.show(np.full((info.height, info.width), 255, np.uint8))
                camera, thermal = [], []
                for view in range(views):
                    if self.board_holder is not None:
                        self.board_holder.present(board, view)
                    else:
                        time.sleep(interval_s)
                    camera.append(self.camera.grab(self.grab_timeout_s))
                    thermal.append(self.thermal.grab(self.grab_timeout_s))
            except DeviceLost:
                self._reopen()
                raise
            finally:
                if self.board_holder is not None:
                    self.board_holder.present(None, -1)
        return BoardViews(camera=np.stack([frame.image for frame in camera]),
                          thermal=np.stack([frame.image for frame in thermal]).astype(np.float32, copy=False),
                          timestamps=np.array([frame.timestamp for frame in camera]),
                          devices=[device.info for device in self.devices])

    def _reopen(self) -> None:
        self.close()
        try:
            self.open()
        except DeviceUnavailable as error:
            logger.warning("device not back after a loss, will retry on the next capture: %s", error)
