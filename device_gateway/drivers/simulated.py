"""The simulated station: the virtual rig's renderer behind the same interfaces as real devices.

The camera films whatever pattern the simulated projector shows, rendered by
``services.simulation.render`` (shadows, shading, texture, blur, noise,
quantisation), or, for a scene with ``temperature`` and ``optics``, by
``services.simulation.glow`` (the part's own glow, cooling from frame to frame,
through a sensor in electrons: 12-bit frames by default). The camera honours
``set_exposure``: a hot scene's frames are exposed for that time, a cold scene's
``CameraEffects.exposure`` scales with it (the default 8 ms gives it as set). The thermal camera sees the scene's temperature field through
``services.simulation.thermal`` (area integration, blur, NETD noise). The scene
geometry is traced once, when the devices are first opened (seconds for a
1280x800 view); every frame after that is one cheap pass plus fresh noise. The
scene is static: a cold scene's noiseless image under a pattern is kept (per
pattern content, a few MB each), so filming the same pattern again adds only the
exposure, fresh noise and quantisation; the gateway has the camera render its
sequence's images when it starts (``prepare``), so the first capture is as fast as
the next; from then on the camera's noise images (standard normal deviates, from a
generator of their own) are drawn on a background thread ahead of the frames that
use them, a sequence's worth, while the gateway waits for the next capture. A hot
scene cools, and is rendered per frame.
By default it is the forging station of ``services.simulation.presets``: the
rig's true calibration is ``presets.forging_rig()``.

For calibration views the station is also the board holder: it puts the board in
a new pose before each view (``present``), and both cameras then film the board
(``services.simulation.boards``: printed for the camera, hollowed before a heater
for the thermal camera) instead of the part.
"""

from __future__ import annotations

import dataclasses
import hashlib
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from device_gateway.devices import (CameraDriver, DeviceInfo, DeviceLost, DeviceUnavailable, Frame, ProjectorDriver,
                                    ThermalDriver)
from services.formats.board import BoardSpec
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.simulation import presets
from services.simulation.boards import render_board
from services.simulation.glow import GlowView, render_glow_view, render_hot_frames
from services.simulation.render import (
    CameraEffects, ProjectorEffects, ViewGeometry, pixel_irradiance, render_view, sensor_levels,
)
from services.simulation.scene import Scene
from services.simulation.thermal import TemperatureScene, ThermalEffects, forging_temperatures, render_thermal


@dataclass(frozen=True)
class SimulationOptions:
    """Sensor models of the simulated devices.

    ``camera_supersample`` sub-samples per camera pixel side: 1 keeps a 1280x800
    frame at tens of milliseconds (the scan's time budget); 3 integrates pixel area.
    """

    camera_effects: CameraEffects = field(default_factory=lambda: CameraEffects(noise_sigma=1.0, blur_sigma=0.5))
    projector_effects: ProjectorEffects = field(default_factory=lambda: ProjectorEffects(blur_sigma=0.5))
    thermal_effects: ThermalEffects = field(default_factory=ThermalEffects)
    camera_supersample: int = 1
    seed: int = 0
    frame_interval_s: float = 1 / 30


# Noiseless pattern images kept (4 MB each at 1280x800): a sequence's 30 patterns, metering frames and more.
_CLEAN_FRAMES_KEPT = 64

# The exposure at which a cold scene's frames follow ``CameraEffects.exposure`` (the OAK driver's default).
REFERENCE_EXPOSURE_US = 8000.0


# The hollowed board before its heater as the thermal camera sees it: holes at the heater's temperature.
_BOARD_COOL_C = 25.0
_BOARD_HEATER_C = 180.0
_BOARD_TILT_DEG = 22.0
_BOARD_SPREAD_MM = 40.0


class NoiseAhead:
    """The camera's standard normal noise images, drawn from ``rng`` in its order, once :meth:`keep_ahead`
    has started it up to ``depth`` of them ahead of the frames on a background thread.

    Drawing one million deviates is most of a cold frame's cost (10..20 ms of 15..25 ms at 1280x800 on a
    busy machine) and numpy's generator releases the GIL while it draws, so between captures the gateway
    draws the next capture's noise. The images come out in the generator's order whoever drew them and
    whenever, so the frames are as reproducible from the seed as when drawn in line.
    """

    def __init__(self, rng: np.random.Generator, shape: tuple[int, int]) -> None:
        self._rng, self.shape = rng, shape
        self._ready: deque[np.ndarray] = deque()
        self._changed = threading.Condition()
        self._depth = 0
        self._drawer: threading.Thread | None = None

    def keep_ahead(self, depth: int) -> None:
        """Keep ``depth`` images drawn ahead from now on (a background thread draws them)."""
        with self._changed:
            self._depth = depth
            if self._drawer is None:
                self._drawer = threading.Thread(target=self._draw_ahead, name="camera-noise", daemon=True)
                self._drawer.start()
            self._changed.notify_all()

    def stop(self) -> None:
        """Stop drawing ahead (the images drawn stay for the next frames)."""
        with self._changed:
            drawer, self._drawer = self._drawer, None
            self._changed.notify_all()
        if drawer is not None:
            drawer.join()

    def standard_normal(self, size: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
        """The next noise image (float32 of the camera's shape), drawn ahead or now."""
        if tuple(size) != self.shape or np.dtype(dtype) != np.float32:
            raise ValueError(f"The camera's noise images are float32 of shape {self.shape}; asked for {dtype} "
                             f"of shape {tuple(size)}.")
        with self._changed:
            self._changed.wait_for(lambda: self._ready or self._drawer is None)
            if self._ready:
                self._changed.notify_all()
                return self._ready.popleft()
            return self._rng.standard_normal(self.shape, dtype=np.float32)  # nothing draws ahead: draw it now

    def _draw_ahead(self) -> None:
        me = threading.current_thread()
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._drawer is not me or len(self._ready) < self._depth)
                if self._drawer is not me:
                    return
            noise = self._rng.standard_normal(self.shape, dtype=np.float32)  # only this thread draws now
            with self._changed:
                self._ready.append(noise)
                self._changed.notify_all()


def board_pose(board: BoardSpec, view: int, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World-from-board pose (R, t) of calibration view ``view``: the board centred near ``centre``, facing the
    devices (its z axis along +z), tilted by 22 degrees about an axis that turns from view to view."""
    import cv2

    turn = 2.4 * view  # radians: successive views spread their tilt axes around the circle
    axis = np.array([np.cos(turn), np.sin(turn), 0.0])
    R = cv2.Rodrigues(axis * np.radians(_BOARD_TILT_DEG))[0]
    offset = _BOARD_SPREAD_MM * np.array([np.cos(1.7 * view), np.sin(1.3 * view), 0.5 * np.sin(0.9 * view)])
    middle = board.object_points().mean(axis=0)
    return R, centre + offset - R @ middle


def _board_in_device(pose: tuple[np.ndarray, np.ndarray], device: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    R_wb, t_wb = pose
    return device.R @ R_wb, device.R @ t_wb + device.t


class SimulatedStation:
    """A scene, its temperatures and the true rig, with one simulated device per rig role.

    Parameters
    ----------
    rig : Rig, optional
        The devices' true calibration; default ``presets.forging_rig()``.
    scene, temperatures : optional
        The part and its temperature field; default the forging preset.
    options : SimulationOptions
        Sensor models and noise seed.
    camera, projector, thermal : str, optional
        Rig device names; default the only device of each kind.
    """

    def __init__(self, rig: Rig | None = None, scene: Scene | None = None,
                 temperatures: TemperatureScene | None = None, options: SimulationOptions = SimulationOptions(),
                 camera: str | None = None, projector: str | None = None, thermal: str | None = None,
                 thermal_image: Callable[[CameraModel], np.ndarray] | None = None) -> None:
        self.rig = rig or presets.forging_rig()
        self.thermal_image = thermal_image
        self.lose_camera_after: int | None = None
        """Fault drills: the camera is lost once, after this many patterns shown since the station opened."""
        self.scene = scene or presets.forging_scene()
        self.temperatures = temperatures or forging_temperatures()
        self.options = options
        self._rng = np.random.default_rng(options.seed)
        self._lock = threading.Lock()
        self._view: ViewGeometry | None = None
        self._glow: GlowView | None = None
        self.clock_s = 0.0  # simulated time since the station opened: a hot part cools with it
        self._clean_thermal: np.ndarray | None = None
        self._clean_frames: dict[bytes, np.ndarray] = {}  # a cold scene's noiseless image per pattern digest
        self._board: tuple[BoardSpec, tuple[np.ndarray, np.ndarray]] | None = None
        self.shown: np.ndarray | None = None
        self.shown_count = 0  # patterns shown since the station opened (fault drills)
        camera_name, _ = self.rig.device(camera, "camera")
        projector_name, _ = self.rig.device(projector, "projector")
        thermal_name, _ = self.rig.device(thermal, "thermal")
        self.camera = SimulatedCamera(self, camera_name)
        camera_size = self.rig.devices[camera_name].size
        self.camera_noise = NoiseAhead(np.random.default_rng(np.random.SeedSequence(options.seed).spawn(1)[0]),
                                       (camera_size[1], camera_size[0]))
        self.projector = SimulatedProjector(self, projector_name)
        self.thermal = SimulatedThermal(self, thermal_name)

    @property
    def hot(self) -> bool:
        """Whether the scene glows (has a temperature field and optics)."""
        return self.scene.temperature is not None and self.scene.optics is not None

    def view(self) -> ViewGeometry:
        """The camera's traced view of the scene under the projector (and of its glow), computed once."""
        with self._lock:
            if self._view is None:
                camera = self.rig.devices[self.camera.name]
                self._view = render_view(self.scene, camera, self.rig.devices[self.projector.name],
                                         self.options.camera_supersample)
                if self.hot:
                    self._glow = render_glow_view(self.scene, camera, self.options.camera_supersample)
            return self._view

    def clean_thermal(self) -> np.ndarray:
        """The thermal camera's noiseless image, computed once (noise is added per frame)."""
        with self._lock:
            if self._clean_thermal is None:
                noiseless = self.options.thermal_effects.model_copy(update={"netd": 0.0})
                if self.thermal_image is not None:
                    self._clean_thermal = self.thermal_image(self.rig.devices[self.thermal.name])
                    return self._clean_thermal
                self._clean_thermal = render_thermal(self.scene, self.temperatures, self.rig.devices[self.thermal.name],
                                                     noiseless, self._rng)
            return self._clean_thermal

    def film(self) -> np.ndarray:
        """The camera frame of the pattern on the projector now (black when it shows nothing)."""
        projector = self.rig.devices[self.projector.name]
        pattern = self.shown if self.shown is not None else np.zeros((projector.height, projector.width), np.uint8)
        view, exposure_us = self.view(), self.camera.exposure_us
        time_s, self.clock_s = self.clock_s, self.clock_s + self.options.frame_interval_s
        if self._glow is not None:
            return render_hot_frames(view, self._glow, pattern[None], exposure_us * 1e-6, self._rng, start_s=time_s,
                                     blur_sigma=self.options.camera_effects.blur_sigma,
                                     projector_effects=self.options.projector_effects)[0]
        effects = self.options.camera_effects
        effects = dataclasses.replace(effects, exposure=effects.exposure * exposure_us / REFERENCE_EXPOSURE_US)
        return sensor_levels(self._clean_frame(view, pattern), effects, self.camera_noise)

    def render_ahead(self, patterns: np.ndarray) -> None:
        """Render a cold scene's noiseless images under ``patterns`` now rather than in the first capture."""
        if not self.hot:
            view = self.view()
            for pattern in patterns:
                self._clean_frame(view, np.asarray(pattern, dtype=np.uint8))

    def _clean_frame(self, view: ViewGeometry, pattern: np.ndarray) -> np.ndarray:
        """The cold scene's pixel irradiance under ``pattern`` before exposure and noise, computed once."""
        key = hashlib.blake2b(np.ascontiguousarray(pattern), digest_size=16).digest()
        with self._lock:
            clean = self._clean_frames.get(key)
        if clean is None:
            clean = pixel_irradiance(view, pattern, self.options.camera_effects, self.options.projector_effects)
            clean.flags.writeable = False
            with self._lock:
                if len(self._clean_frames) >= _CLEAN_FRAMES_KEPT:
                    self._clean_frames.clear()
                self._clean_frames[key] = clean
        return clean

    def present(self, board: BoardSpec | None, view: int) -> None:
        """Hold ``board`` in the pose of calibration view ``view`` before the devices, or take it away."""
        aim = np.asarray(presets.FORGING_AIM, dtype=np.float64)
        self._board = None if board is None else (board, board_pose(board, view, aim))

    def board_frame(self, device_name: str, modality: str) -> np.ndarray | None:
        """The device's view of the held board (None when no board is held): 8-bit for the camera,
        16-bit radiance for the thermal camera."""
        if self._board is None:
            return None
        board, pose = self._board
        device = self.rig.devices[device_name]
        R, t = _board_in_device(pose, device)
        effects = self.options.camera_effects
        return render_board(board, device.K, device.dist, R, t, device.size, modality=modality,
                            blur_sigma=max(effects.blur_sigma, 0.3), noise_sigma=effects.noise_sigma,
                            bit_depth=8 if modality == "visible" else 16, rng=self._rng)

    def thermal_noise(self, shape: tuple[int, ...]) -> np.ndarray:
        return self._rng.normal(0.0, self.options.thermal_effects.netd, shape)


class _SimulatedDevice:
    kind: str

    def __init__(self, station: SimulatedStation, name: str) -> None:
        self.station = station
        self.name = name
        self._open = False

    @property
    def info(self) -> DeviceInfo:
        device = self.station.rig.devices[self.name]
        return DeviceInfo(self.name, self.kind, "simulated", device.width, device.height, model="virtual rig")

    @property
    def is_open(self) -> bool:
        return self._open

    def close(self) -> None:
        self._open = False

    def _require_open(self) -> None:
        if not self._open:
            raise DeviceUnavailable(f"{self.kind} {self.name!r} is not open")


class SimulatedCamera(_SimulatedDevice, CameraDriver):
    kind = "camera"

    def __init__(self, station: SimulatedStation, name: str) -> None:
        super().__init__(station, name)
        self._exposure_us = 1000.0 if station.hot else REFERENCE_EXPOSURE_US
        self._frames_per_capture = 0  # known once prepared: that many frames' noise is drawn ahead while open

    @property
    def exposure_us(self) -> float:
        return self._exposure_us

    def set_exposure(self, exposure_us: float) -> None:
        if not exposure_us > 0:
            raise ValueError(f"The exposure must be a positive number of microseconds; got {exposure_us}.")
        self._exposure_us = float(exposure_us)

    @property
    def saturation_level(self) -> int:
        if self.station.hot:
            return self.station.scene.optics.sensor.full_scale
        return self.station.options.camera_effects.full_scale

    def open(self) -> None:
        self.station.view()
        self._open = True
        self._draw_noise_ahead()

    def prepare(self, patterns: np.ndarray) -> None:
        self._require_open()
        self.station.render_ahead(patterns)
        self._frames_per_capture = len(patterns)
        self._draw_noise_ahead()

    def close(self) -> None:
        super().close()
        self.station.camera_noise.stop()

    def _draw_noise_ahead(self) -> None:
        if self._frames_per_capture and not self.station.hot:  # a hot scene's frames are rendered whole per frame
            self.station.camera_noise.keep_ahead(self._frames_per_capture)

    def grab(self, timeout_s: float) -> Frame:
        self._require_open()
        lose_after = self.station.lose_camera_after
        if lose_after is not None and self.station.shown_count >= lose_after:
            self.station.lose_camera_after = None  # lost once: back when re-opened
            raise DeviceLost(f"camera {self.name!r}: connection lost (simulated fault)")
        exposed = time.time()
        board = self.station.board_frame(self.name, "visible")
        return Frame(self.station.film() if board is None else board, exposed,
                     {"driver": "simulated", "exposure_us": self._exposure_us})


class SimulatedThermal(_SimulatedDevice, ThermalDriver):
    kind = "thermal"

    def open(self) -> None:
        self.station.clean_thermal()
        self._open = True

    def grab(self, timeout_s: float) -> Frame:
        self._require_open()
        board = self.station.board_frame(self.name, "infrared")
        if board is not None:
            clean = _BOARD_COOL_C + (_BOARD_HEATER_C - _BOARD_COOL_C) * board.astype(np.float64) / 65535.0
        else:
            clean = self.station.clean_thermal()
        image = (clean + self.station.thermal_noise(clean.shape)).astype(np.float32)
        return Frame(image, time.time(), {"driver": "simulated", "units": "degC"})


class SimulatedProjector(_SimulatedDevice, ProjectorDriver):
    kind = "projector"

    @property
    def settle_s(self) -> float:
        return 0.0

    def open(self) -> None:
        self._open = True

    def show(self, pattern: np.ndarray) -> None:
        self._require_open()
        self.station.shown = np.asarray(pattern, dtype=np.uint8)
        self.station.shown_count += 1


def simulated_station_heads(heads: int = 4, scale: float = 1.0, dent_depth_mm: float = 0.0,
                            lose_head: str | None = None,
                            options: SimulationOptions = SimulationOptions()) -> tuple[list, dict, Rig]:
    """The devices of the simulated station of several heads around the hot shaft
    (``services.simulation.station.station_scene``; its true rig ``presets.station_rig(scale, heads)``).

    Each head is a :class:`SimulatedStation` of that head's camera and projector filming the shaft's scene (its
    glow and its own projector's light); the thermal cameras read the hot part as
    ``hot_part.simulated_thermal_frame`` renders it. ``lose_head`` names a head whose camera is lost half way
    through the first capture (fault drills; re-opened, it films the next).

    Returns
    -------
    heads : list of device_gateway.station.StationHead
    thermals : dict of thermal device name to SimulatedThermal
    rig : Rig
        The station's true calibration.
    """
    from device_gateway.station import StationHead
    from services.simulation.hot_part import simulated_thermal_frame
    from services.simulation.station import station_scene

    station = station_scene(heads=heads, scale=scale, dent_depth_mm=dent_depth_mm)
    rig = station.rig
    noiseless = options.thermal_effects.model_copy(update={"netd": 0.0})
    rng = np.random.default_rng(options.seed)

    def thermal_image(device: CameraModel) -> np.ndarray:
        return simulated_thermal_frame(station.part, device, rng, effects=noiseless)

    thermal_names = [name for name, device in rig.devices.items() if device.kind == "thermal"]
    if lose_head is not None and lose_head not in [head.name for head in rig.heads]:
        raise ValueError(f"The simulated station has no head {lose_head!r}; its heads are "
                         f"{[head.name for head in rig.heads]}.")
    stations, thermals = [], {}
    for index, head in enumerate(rig.heads):
        simulated = SimulatedStation(rig=rig, scene=station.scene, temperatures=station.scene.temperature,
                                     options=dataclasses.replace(options, seed=options.seed + index),
                                     camera=head.camera, projector=head.projector,
                                     thermal=thermal_names[index % len(thermal_names)], thermal_image=thermal_image)
        if head.name == lose_head:
            simulated.lose_camera_after = 12
        stations.append(StationHead(head.name, simulated.camera, simulated.projector))
        if simulated.thermal.name not in thermals:
            thermals[simulated.thermal.name] = simulated.thermal
    return stations, thermals, rig
