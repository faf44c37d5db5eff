"""The simulated station: N sensor heads around a hot carbon-steel shaft, filmed head after head, with the truth.

The shaft (300 mm long, 90 mm in diameter cold, carbon steel at about 1000 degC, axis along world x, held
horizontally; ``presets.station_rig`` places the heads) is a ``hot_part.HotPart``: its cold mesh, an
optional dent, expanded by its temperature field. Each head films it as the single-head hot-part
station does (``render.render_view`` for the projector's light, ``glow.render_glow_view`` and
``glow.render_hot_frames`` for the part's own glow through a 450/40 nm filter under a blue projector,
the project's sequence closed by a black frame), lit by its own projector only: the gateway runs the
heads one after another. The exposure is what the gateway's automatic exposure chooses (the white
frame's 99.9th percentile at 85 % of saturation), computed from the noiseless white frame. Each
thermal camera takes one frame (``hot_part.simulated_thermal_frame``), once for all heads.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.formats.rig import Rig
from services.formats.sequence import Sequence
from services.formats.station_capture import HeadFrames, save_station_capture
from services.inspection.materials import builtin_material
from services.simulation.glow import render_glow_view, render_hot_frames
from services.simulation.hot_part import Bump, HotPart, cylinder_mesh, simulated_thermal_frame
from services.simulation.optics import Optics, SensorOptics
from services.simulation.presets import (HOT_STEEL_EMISSIVITY, STATION_SHAFT_LENGTH_MM, STATION_SHAFT_RADIUS_MM,
                                         hot_optics, station_head_meridian, station_rig)
from services.simulation.render import GroundTruth, ProjectorEffects, integrate_pixels, render_view, sample_irradiance
from services.simulation.scene import Albedo, Scene
from services.simulation.temperature import SurfaceTemperature, TemperatureScene
from services.simulation.thermal import ThermalEffects
from services.structured_light.patterns import generate_sequence

SHAFT_TEMPERATURE_C = 1000.0
SHAFT_GRADIENT_K_PER_MM = 0.1
"""Along the axis: the +x end 30 K hotter than the -x end, so that the field shows a temperature."""
DENT_SIGMA_MM = 8.0
DENT_AXIAL_MM = 40.0
EXPOSURE_TARGET = 0.85
_SEGMENTS = 360


@dataclass(frozen=True)
class ShaftTruth:
    """The true cold shaft: diameter and length between the end faces (mm), and the dent (None without)."""

    diameter_mm: float
    length_mm: float
    dent: Bump | None


@dataclass(frozen=True)
class StationScene:
    """The station's true rig, the hot shaft, the scene the heads film and the truth."""

    rig: Rig
    part: HotPart
    scene: Scene
    truth: ShaftTruth


@dataclass(frozen=True)
class HeadShot:
    """One head's capture and the truth at its camera's pixels (``render.GroundTruth``)."""

    capture: HeadFrames
    truth: GroundTruth
    exposure_s: float


@dataclass(frozen=True)
class StationCapture:
    """What the station films: every head's capture, and one frame per thermal camera (degrees C)."""

    heads: tuple[HeadShot, ...]
    thermal: Mapping[str, np.ndarray]

    def save(self, directory: str | Path) -> Path:
        """Write it in the station capture layout (services/formats/station_capture.py)."""
        return save_station_capture(directory, tuple(shot.capture for shot in self.heads), self.thermal)


def station_optics() -> Optics:
    """A 30 W blue projector through a 450/40 nm filter, as the hot-part station's; an 8-bit sensor, so that the
    frames are saturated at their files' maximum (the shot noise of its full well outweighs the coarser steps)."""
    optics = hot_optics("blue", (450.0, 40.0))
    return optics.model_copy(update={"sensor": SensorOptics(bit_depth=8)})


def station_scene(*, heads: int = 4, scale: float = 1.0, dent_depth_mm: float = 0.0,
                  temperature_c: float = SHAFT_TEMPERATURE_C, diameter_mm: float = 2 * STATION_SHAFT_RADIUS_MM,
                  length_mm: float = STATION_SHAFT_LENGTH_MM) -> StationScene:
    """The simulated station: ``presets.station_rig(scale, heads)`` around the hot shaft.

    Parameters
    ----------
    heads : int
        Sensor heads around the shaft.
    scale : float
        Shrinks the heads' images and focal lengths (fast tests).
    dent_depth_mm : float
        Depth of a smooth dent (Gaussian, sigma 8 mm) on the side facing away from the first head, 40 mm
        from the centre along the axis; 0 for none.
    temperature_c : float
        The shaft's temperature at its centre; it rises by 0.1 K/mm along +x.
    diameter_mm, length_mm : float
        The true cold shaft's size (a part made off its nominal 90 x 300 mm).

    Returns
    -------
    StationScene
    """
    if dent_depth_mm < 0:
        raise ValueError(f"A dent's depth is positive (or 0 for none); got {dent_depth_mm} mm.")
    if not (diameter_mm > 0 and length_mm > 0):
        raise ValueError(f"The shaft's diameter and length are positive; got {diameter_mm} and {length_mm} mm.")
    rig = station_rig(scale, heads)
    vertices, triangles = cylinder_mesh(diameter_mm / 2, length_mm, _SEGMENTS)
    dent = None
    if dent_depth_mm > 0:
        away = -station_head_meridian(0, heads)
        centre = np.array([DENT_AXIAL_MM, 0.0, 0.0]) + diameter_mm / 2 * away
        dent = Bump(center=tuple(float(c) for c in centre), sigma_mm=DENT_SIGMA_MM, height_mm=-dent_depth_mm)
    temperature = SurfaceTemperature(base=temperature_c, gradient=[SHAFT_GRADIENT_K_PER_MM, 0.0, 0.0])
    part = HotPart(vertices, triangles, builtin_material("carbon-steel"), temperature,
                   bumps=() if dent is None else (dent,), centre=(0.0, 0.0, 0.0))
    albedo = Albedo(base=1 - HOT_STEEL_EMISSIVITY, texture_amplitude=0.02, feature_size=25.0, seed=7)
    scene = Scene(surfaces=[part.surface().model_copy(update={"albedo": albedo})], ambient=0.01,
                  temperature=TemperatureScene(background=25.0, surfaces=[temperature]), optics=station_optics())
    truth = ShaftTruth(diameter_mm=diameter_mm, length_mm=length_mm, dent=dent)
    return StationScene(rig=rig, part=part, scene=scene, truth=truth)


def station_sequence(rig: Rig) -> tuple[Sequence, np.ndarray]:
    """The heads' sequence (all heads' projectors are alike): the project's default, coding projector rows (the
    heads' baselines run across their images' short side), closed by a black frame for the glow."""
    from services.structured_light.reconstruct import coded_axis

    head = rig.heads[0]
    camera, projector = rig.devices[head.camera], rig.devices[head.projector]
    axis = coded_axis(("x", "y"), camera, projector)
    return generate_sequence(projector.width, projector.height, axes=axis, closing_black=True)


def film_station(station: StationScene, *, seed: int = 0, supersample: int = 1, blur_sigma: float = 0.5,
                 thermal_effects: ThermalEffects = ThermalEffects()) -> StationCapture:
    """Film the station: every head's sequence lit by its own projector, then one frame per thermal camera.

    Parameters
    ----------
    station : StationScene
    seed : int
        Noise seed (frames are deterministic given it).
    supersample : int
        Odd camera sub-samples per pixel side (1: the gateway's simulated camera).
    blur_sigma : float
        Camera and projector defocus, pixels.
    thermal_effects : ThermalEffects
        The thermal cameras' area integration, blur and noise.

    Returns
    -------
    StationCapture
    """
    rng = np.random.default_rng(seed)
    rig = station.rig
    sequence, patterns = station_sequence(rig)
    projector_effects = ProjectorEffects(blur_sigma=blur_sigma)
    optics = station.scene.optics
    shots = []
    for head in rig.heads:
        camera, projector = rig.devices[head.camera], rig.devices[head.projector]
        view = render_view(station.scene, camera, projector, supersample)
        glow = render_glow_view(station.scene, camera, supersample)
        white = np.full((projector.height, projector.width), 255, dtype=np.uint8)
        irradiance = integrate_pixels(sample_irradiance(view, white, projector_effects) + glow.glow(0.0), supersample)
        brightest = float(np.percentile(irradiance, 99.9))
        exposure_s = EXPOSURE_TARGET * optics.sensor.full_well_e / (optics.white_rate * max(brightest, 1e-6))
        frames = render_hot_frames(view, glow, patterns, exposure_s, rng, blur_sigma=blur_sigma,
                                   projector_effects=projector_effects)
        shots.append(HeadShot(HeadFrames(head.name, sequence, frames), view.truth, exposure_s))
    thermal = {name: simulated_thermal_frame(station.part, device, rng, effects=thermal_effects)
               for name, device in rig.devices.items() if device.kind == "thermal"}
    return StationCapture(tuple(shots), thermal)


def lateral_coverage(points: np.ndarray, station: StationScene, cell_mm: float = 2.0,
                     tolerance_mm: float = 0.5) -> float:
    """Share of the hot shaft's lateral surface holding a point: the surface divided into cells of about
    ``cell_mm`` (along the axis and round it), the share of cells with a point within ``tolerance_mm`` of the
    surface. The rims (one cell from each end face) are left out."""
    part = station.part
    hot = part.hot_vertices_part()
    radius = float(np.median(np.hypot(hot[:, 1], hot[:, 2])))
    half = float(hot[:, 0].max())
    local = (np.asarray(points, dtype=np.float64) - part.pose[:3, 3]) @ part.pose[:3, :3]
    on_side = (np.abs(np.hypot(local[:, 1], local[:, 2]) - radius) <= tolerance_mm) & \
              (np.abs(local[:, 0]) < half - cell_mm)
    along_cells = int(np.floor(2 * (half - cell_mm) / cell_mm))
    round_cells = int(np.round(2 * np.pi * radius / cell_mm))
    along = np.floor((local[on_side, 0] + half - cell_mm) / cell_mm).astype(int)
    around = np.floor((np.arctan2(local[on_side, 2], local[on_side, 1]) + np.pi) / (2 * np.pi) * round_cells)
    around = np.clip(around.astype(int), 0, round_cells - 1)
    inside = (along >= 0) & (along < along_cells)
    occupied = np.unique(along[inside] * round_cells + around[inside])
    return len(occupied) / (along_cells * round_cells)
