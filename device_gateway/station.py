"""A station: one camera, one thermal camera and one projector, captured together.

A capture shows each pattern, waits for the projector to settle, grabs the camera
frame, and after the last pattern grabs the thermal frame(s). Its exposure is the
camera's own (``fixed``), or metered first (``auto``: a projector-off and a full-white
frame, so that the part's glow plus the full pattern stays below saturation), or
metered and filmed at several exposures merged per pixel (``hdr``: a glowing part
and a cool fixture in one view); the chosen exposures and the glow level go into
``Capture.exposure``. Captures are
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
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np

from device_gateway.devices import (
    CameraDriver, DeviceDriver, DeviceInfo, DeviceLost, DeviceUnavailable, ProjectorDriver, ThermalDriver,
)
from services.formats.board import BoardSpec
from services.formats.sequence import Sequence
from services.structured_light.hdr import merge_exposures

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
    exposure: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ExposureControl:
    """How a capture is exposed.

    ``fixed`` keeps the camera's exposure. ``auto`` meters first: a frame with the projector dark (the
    glow and ambient light) and one fully white, shortened until it no longer saturates; the exposure
    is then set so that the white frame's 99.9th percentile (glow plus full pattern) reaches ``target``
    of saturation. ``hdr`` films the sequence ``hdr_repeats`` times at that exposure and once at each of
    ``hdr_exposures - 1`` more, each ``hdr_ratio`` times longer, and merges them per pixel
    (``structured_light.hdr.merge_exposures``: the exposure-weighted mean of the unsaturated ones). The
    repeats collect the photons that a glowing part's pattern lacks where every longer exposure
    saturates (signal-to-noise ratio with the square root of their number); the longer exposures
    collect them on a cool fixture.
    """

    mode: Literal["fixed", "auto", "hdr"] = "fixed"
    target: float = 0.85
    hdr_exposures: int = 2
    hdr_ratio: float = 4.0
    hdr_repeats: int = 4
    min_exposure_us: float = 10.0
    max_exposure_us: float = 100_000.0

    def __post_init__(self) -> None:
        if not 0 < self.target < 1:
            raise ValueError(f"The exposure target must be a fraction of saturation in (0, 1); got {self.target}.")
        if self.hdr_exposures < 2 or self.hdr_ratio <= 1:
            raise ValueError("HDR needs at least 2 exposures, each more than 1x longer than the last.")
        if self.hdr_repeats < 1:
            raise ValueError(f"HDR films its shortest exposure at least once; got hdr_repeats={self.hdr_repeats}.")
        if not 0 < self.min_exposure_us < self.max_exposure_us:
            raise ValueError("The exposure limits must satisfy 0 < min_exposure_us < max_exposure_us.")


_METERING_PERCENTILE = 99.9
_GLOW_PERCENTILE = 99.0
_METERING_TRIES = 8


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


class _Devices:
    """Open, close and report the health of a station's ``devices`` (a property of the subclass)."""

    devices: list[DeviceDriver]

    def open(self) -> None:
        """Open every device that is not open yet; :class:`DeviceUnavailable` names the first that fails (the
        others are opened all the same, so that health tells which device is missing)."""
        failure: DeviceUnavailable | None = None
        for device in self.devices:
            if not device.is_open:
                try:
                    device.open()
                except DeviceUnavailable as error:
                    failure = failure or error
        if failure is not None:
            raise failure

    def close(self) -> None:
        for device in self.devices:
            device.close()

    def health(self) -> dict[str, bool]:
        """Whether each device (by name) is open and usable."""
        return {device.info.name: device.is_open for device in self.devices}

    def _reopen(self) -> None:
        self.close()
        try:
            self.open()
        except DeviceUnavailable as error:
            logger.warning("device not back after a loss, will retry on the next capture: %s", error)


class Station(_Devices):
    """The devices of one station, owned by the gateway process.

    ``board_holder`` moves the board between calibration views; None means a person does, given
    ``interval_s`` seconds per view.
    """

    def __init__(self, camera: CameraDriver, thermal: ThermalDriver, projector: ProjectorDriver,
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
    def devices(self) -> list[DeviceDriver]:
        return [self.camera, self.thermal, self.projector]

    def capture(self, sequence: Sequence, patterns: np.ndarray, thermal_frames: int = 1,
                exposure: ExposureControl = ExposureControl()) -> Capture:
        """Project ``patterns`` one by one, film each, then grab ``thermal_frames`` thermal frames.

        Parameters
        ----------
        sequence : Sequence
            The manifest describing ``patterns``, returned with the frames.
        patterns : (F, H, W) uint8 array
            One image per manifest frame, at the projector's resolution.
        thermal_frames : int
            Thermal frames to grab after the last pattern.
        exposure : ExposureControl
            Fixed, automatic or HDR exposure (automatic and HDR need a camera that sets its exposure).

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
                return self._capture(sequence, patterns, thermal_frames, exposure)
            except DeviceLost:
                self._reopen()
                raise

    def _film(self, patterns: np.ndarray) -> list:
        frames = []
        for pattern in patterns:
            self.projector.show(pattern)
            if self.settle_s > 0:
                time.sleep(self.settle_s)
            frames.append(self.camera.grab(self.grab_timeout_s))
        return frames

    def meter(self, control: ExposureControl) -> tuple[float, float]:
        """Choose the exposure for a glowing part: (exposure in us, glow level as a fraction of saturation).

        A projector-dark and a full-white frame are filmed at the camera's exposure, shortened eightfold
        while the white frame saturates; the exposure then scales so that the white frame's 99.9th
        percentile (glow plus the full pattern) reaches ``control.target`` of saturation, within the limits.
        """
        info = self.projector.info
        dark_and_white = np.stack([np.zeros((info.height, info.width), np.uint8),
                                   np.full((info.height, info.width), 255, np.uint8)])
        saturation = float(self.camera.saturation_level)
        exposure_us = float(self.camera.exposure_us or control.max_exposure_us)
        for _ in range(_METERING_TRIES):
            exposure_us = min(max(exposure_us, control.min_exposure_us), control.max_exposure_us)
            self.camera.set_exposure(exposure_us)
            dark, white = (frame.image.astype(np.float64) for frame in self._film(dark_and_white))
            bright = float(np.percentile(white, _METERING_PERCENTILE))
            if bright < 0.98 * saturation or exposure_us <= control.min_exposure_us:
                break
            exposure_us /= 8
        chosen = exposure_us * control.target * saturation / max(bright, 1.0)
        chosen = min(max(chosen, control.min_exposure_us), control.max_exposure_us)
        glow = float(np.percentile(dark, _GLOW_PERCENTILE)) * chosen / exposure_us / saturation
        return chosen, glow

    def _capture(self, sequence: Sequence, patterns: np.ndarray, thermal_frames: int,
                 control: ExposureControl) -> Capture:
        frames, camera_frames, metadata = self.film_sequence(patterns, control)
        thermal = [self.thermal.grab(self.grab_timeout_s) for _ in range(thermal_frames)]
        return Capture(
            sequence=sequence,
            frames=frames,
            frame_timestamps=np.array([frame.timestamp for frame in camera_frames]),
            frame_metadata=[{**frame.metadata, "file": entry.file}
                            for frame, entry in zip(camera_frames, sequence.frames)],
            thermal=np.stack([frame.image for frame in thermal]).astype(np.float32, copy=False),
            thermal_timestamps=np.array([frame.timestamp for frame in thermal]),
            thermal_metadata=[frame.metadata for frame in thermal],
            devices=[device.info for device in self.devices],
            exposure=metadata,
        )

    def film_sequence(self, patterns: np.ndarray, control: ExposureControl) -> tuple[np.ndarray, list, dict[str, Any]]:
        """Film ``patterns`` with the camera as ``control`` exposes it (the caller holds the devices): the frames
        (F, H, W), the last exposure's camera frames (timestamps, metadata) and the exposure record."""
        saturation = self.camera.saturation_level
        metadata: dict[str, Any] = {"mode": control.mode, "saturation_level": saturation}
        if control.mode == "fixed":
            camera_frames = self._film(patterns)
            frames = np.stack([frame.image for frame in camera_frames])
            metadata["exposures_us"] = [self.camera.exposure_us]
        else:
            chosen, glow = self.meter(control)
            exposures = [chosen] if control.mode == "auto" else [chosen] * control.hdr_repeats + [
                min(chosen * control.hdr_ratio**k, control.max_exposure_us) for k in range(1, control.hdr_exposures)]
            stacks = []
            for exposure_us in exposures:
                self.camera.set_exposure(exposure_us)
                camera_frames = self._film(patterns)
                stacks.append(np.stack([frame.image for frame in camera_frames]))
            frames = stacks[0]
            if len(stacks) > 1:
                frames, saturation = merge_exposures(np.stack(stacks), exposures, saturation)
            metadata.update(exposures_us=[round(e, 2) for e in exposures], glow_level=round(glow, 5),
                            saturation_level=saturation)
            self.camera.set_exposure(chosen)
        return frames, camera_frames, metadata

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


@dataclass(frozen=True)
class HeadCapture:
    """One head's part of a station capture: its frames (F, H, W) in the sequence's order with their timestamps,
    metadata (each frame's ``head`` and ``file``) and exposure record; or, when a device of the head was lost
    while it filmed, no frames and ``error`` saying which and why."""

    head: str
    frames: np.ndarray
    frame_timestamps: np.ndarray
    frame_metadata: list[dict[str, Any]]
    exposure: dict[str, Any] = field(default_factory=dict)
    error: str | None = None


@dataclass(frozen=True)
class StationCapture:
    """What one capture of a station of several heads returns: every head's capture in the rig's head order
    (each filmed with the same ``sequence``, lit by its own projector only), then ``thermal`` (T, h, w) float32
    degrees C per thermal camera (by the rig's device name), taken once for all heads."""

    sequence: Sequence
    heads: tuple[HeadCapture, ...]
    thermal: dict[str, np.ndarray]
    thermal_timestamps: dict[str, np.ndarray]
    devices: list[DeviceInfo]


@dataclass(frozen=True)
class StationHead:
    """A sensor head of a station: its name in the rig file, its camera and the projector whose patterns it films."""

    name: str
    camera: CameraDriver
    projector: ProjectorDriver


class MultiHeadStation(_Devices):
    """The devices of a station of several heads (a version-2 rig's ``heads``) and its thermal cameras.

    A capture runs the heads one after another (time multiplexing: each head's projector shows the sequence,
    each head's camera films it, the other projectors dark), then grabs the thermal frames once for all heads.
    A head whose device is lost mid-capture does not stop the others: its :class:`HeadCapture` says which
    device and why (``error``), its devices are re-opened, and the capture goes on; a lost thermal camera fails
    the capture (:class:`DeviceLost`), as on a single-head station.
    """

    def __init__(self, heads: list[StationHead], thermals: dict[str, ThermalDriver], settle_s: float | None = None,
                 grab_timeout_s: float = 2.0) -> None:
        if len(heads) < 1 or not thermals:
            raise ValueError("A station needs at least one head and one thermal camera.")
        self.heads = heads
        self.thermals = thermals
        self._thermal = next(iter(thermals.values()))
        self._stations = [Station(head.camera, self._thermal, head.projector, settle_s=settle_s,
                                  grab_timeout_s=grab_timeout_s) for head in heads]
        self.grab_timeout_s = grab_timeout_s
        self._lock = threading.Lock()

    @property
    def projector(self) -> ProjectorDriver:
        """The first head's projector (all heads project the same sequence)."""
        return self.heads[0].projector

    @property
    def devices(self) -> list[DeviceDriver]:
        heads = [device for head in self.heads for device in (head.camera, head.projector)]
        return heads + list(self.thermals.values())

    def prepare(self, patterns: np.ndarray) -> None:
        """Let every head's camera prepare for ``patterns`` (the simulated ones render them ahead)."""
        for head in self.heads:
            head.camera.prepare(patterns)

    def capture(self, sequence: Sequence, patterns: np.ndarray, thermal_frames: int = 1,
                exposure: ExposureControl = ExposureControl()) -> StationCapture:
        """Film ``patterns`` head after head, then grab ``thermal_frames`` frames of every thermal camera.

        Raises
        ------
        ValueError
            As :meth:`Station.capture`.
        DeviceUnavailable
            When a device cannot be opened before the capture.
        DeviceLost
            When a thermal camera stops answering (a head's lost device is reported in its capture instead).
        """
        patterns = np.asarray(patterns)
        if len(patterns) != len(sequence.frames) or thermal_frames < 1:
            raise ValueError(f"The manifest lists {len(sequence.frames)} frames and {len(patterns)} patterns were "
                             f"given, with {thermal_frames} thermal frames (at least one is needed).")
        with self._lock:
            self.open()
            dark = np.zeros(patterns.shape[1:], np.uint8)
            for head in self.heads:
                head.projector.show(dark)
            heads = []
            for head, station in zip(self.heads, self._stations):
                heads.append(self._film_head(head, station, sequence, patterns, exposure, dark))
            try:
                thermal = {name: [device.grab(self.grab_timeout_s) for _ in range(thermal_frames)]
                           for name, device in self.thermals.items()}
            except DeviceLost:
                self._reopen()
                raise
        return StationCapture(
            sequence=sequence, heads=tuple(heads),
            thermal={name: np.stack([f.image for f in frames]).astype(np.float32, copy=False)
                     for name, frames in thermal.items()},
            thermal_timestamps={name: np.array([f.timestamp for f in frames]) for name, frames in thermal.items()},
            devices=[device.info for device in self.devices])

    def _film_head(self, head: StationHead, station: Station, sequence: Sequence, patterns: np.ndarray,
                   exposure: ExposureControl, dark: np.ndarray) -> HeadCapture:
        try:
            frames, camera_frames, metadata = station.film_sequence(patterns, exposure)
            head.projector.show(dark)
        except (DeviceLost, DeviceUnavailable) as error:
            logger.warning("head %r lost a device mid-capture: %s", head.name, error)
            for device in (head.camera, head.projector):
                device.close()
            try:
                for device in (head.camera, head.projector):
                    device.open()
            except DeviceUnavailable as reopened:
                logger.warning("head %r not back after a loss, will retry on the next capture: %s", head.name,
                               reopened)
            empty = np.zeros((0, 0, 0), np.uint8)
            return HeadCapture(head.name, empty, np.zeros(0), [], {}, f"head {head.name!r}: {error}")
        return HeadCapture(head.name, frames, np.array([frame.timestamp for frame in camera_frames]),
                           [{**frame.metadata, "head": head.name, "file": entry.file}
                            for frame, entry in zip(camera_frames, sequence.frames)], metadata)

