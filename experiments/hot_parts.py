"""Hot parts: a glowing billet and dome before a cool fixture plate, scanned through the simulated station.

Run:  .venv/bin/python experiments/hot_parts.py [--scale 1.0] [--figure docs/figures/hot-parts.png]
      .venv/bin/python experiments/hot_parts.py --ablation   (white 1000 C HDR: each remedy alone and both)

Every case films ``presets.hot_part_scene`` with the forging rig's projector and camera through the
simulated gateway (``SimulatedStation`` behind a ``Station``: metering, automatic exposure or HDR, the
part cooling from frame to frame), reconstructs with ``reconstruct_scan`` and compares every point with
the simulator's ground truth at its camera pixel. ``--scale`` shrinks the camera (focal length and
size) for quick runs; the tests use 0.3 and 0.5.

Measures, per surface group (the part: billet and dome; the fixture plate):
- reconstructed: share of the lit pixels whose 4-neighbours see the same surface (a pixel straddling
  the part's silhouette mixes two depths and belongs to neither) that have a point;
- mean error: mean distance from the true surface point at the pixel centre, over the part's points;
- off > 1 mm: share of all points whose pixel centre sees the part that are more than 1 mm off
  (silhouette pixels included).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from device_gateway.drivers.simulated import SimulatedStation, SimulationOptions
from device_gateway.station import ExposureControl, Station
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.simulation.presets import HOT_STEEL_EMISSIVITY, forging_rig, hot_optics, hot_part_scene
from services.simulation.render import CameraEffects, ProjectorEffects
from services.simulation.thermal import ThermalEffects
from services.structured_light.patterns import generate_sequence
from services.structured_light.reconstruct import GLOW_WINDOW_SIGMA_PX, Reconstruction, reconstruct_scan

PART_SURFACES = (0, 1)
FIXTURE_SURFACE = 2
FRAME_INTERVAL_S = 1 / 30


@dataclass(frozen=True)
class Case:
    name: str
    peak_c: float
    projector: str  # "white" or "blue"
    band_pass: tuple[float, float] | None
    exposure: str  # "auto" or "hdr"
    drift_k: float = 0.0  # cooling over the sequence's frames
    hdr_repeats: int = ExposureControl.hdr_repeats  # films of the shortest exposure
    window: bool = True  # pixels lost to the glow's noise decoded again over a window


CASES = (
    Case("blue 450/40, 1200 C, auto", 1200.0, "blue", (450.0, 40.0), "auto"),
    Case("blue 450/40, 1200 C, auto, drift 5 K", 1200.0, "blue", (450.0, 40.0), "auto", 5.0),
    Case("white, 1000 C, auto", 1000.0, "white", None, "auto"),
    Case("white, 1000 C, auto, drift 5 K", 1000.0, "white", None, "auto", 5.0),
    Case("white, 1000 C, HDR", 1000.0, "white", None, "hdr"),
    Case("white, 1250 C, auto", 1250.0, "white", None, "auto"),
    Case("white, 1250 C, HDR", 1250.0, "white", None, "hdr"),
)

ABLATION = tuple(Case("white, 1000 C, HDR", 1000.0, "white", None, "hdr", hdr_repeats=repeats, window=window)
                 for repeats, window in ((1, False), (1, True), (4, False), (8, False), (4, True)))
"""What the repeated short exposure and the windowed decoding each contribute (``--ablation``)."""


def ratio_table() -> str:
    """The model's glow-to-pattern ratios (part albedo 0.15, normal incidence) for the docs."""
    temperatures = (900.0, 1000.0, 1100.0, 1200.0, 1250.0)
    setups = (("white LED 20 W, no filter", hot_optics("white")),
              ("blue LED 30 W, 450/40 filter", hot_optics("blue", (450.0, 40.0))),
              ("blue LED 30 W, no filter", hot_optics("blue")))
    lines = ["| projector, camera filter | " + " | ".join(f"{t:.0f} C" for t in temperatures) + " |",
             "|---|" + "---|" * len(temperatures)]
    for name, optics in setups:
        ratios = optics.glow_to_pattern(np.array(temperatures), 1 - HOT_STEEL_EMISSIVITY)
        lines.append(f"| {name} | " + " | ".join(f"{r:.3g}" for r in ratios) + " |")
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Result:
    case: Case
    exposures_us: list[float]
    glow_level: float
    part_reconstructed: float
    fixture_reconstructed: float
    part_mean_error_mm: float
    part_off_1mm: float
    scan: Reconstruction
    frames: np.ndarray
    depth_map: np.ndarray  # camera-frame z of the reconstructed points, NaN elsewhere


def scaled_rig(scale: float) -> Rig:
    """The forging rig with its camera's size and focal length scaled (the projector unchanged)."""
    rig = forging_rig()
    camera = rig.devices["camera"]
    width, height = round(camera.width * scale), round(camera.height * scale)
    K = np.asarray(camera.K, dtype=np.float64)
    K_scaled = [[K[0, 0] * scale, 0.0, (width - 1) / 2], [0.0, K[1, 1] * scale, (height - 1) / 2], [0.0, 0.0, 1.0]]
    devices = dict(rig.devices)
    devices["camera"] = CameraModel(kind="camera", width=width, height=height, K=K_scaled, dist=camera.dist,
                               R=camera.R, t=camera.t)
    return Rig(devices=devices)


def _interior(surface: np.ndarray) -> np.ndarray:
    """Pixels whose 4-neighbours see the same surface."""
    same = surface.copy()
    inside = np.zeros(surface.shape, dtype=bool)
    inside[1:-1, 1:-1] = True
    for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
        inside &= np.roll(same, shift, axis=axis) == same
    return inside


def run_case(case: Case, scale: float = 1.0, seed: int = 0) -> Result:
    """Film, reconstruct and score one case."""
    rig = scaled_rig(scale)
    sequence, patterns = generate_sequence(1280, 800, closing_black=True)
    cooling = case.drift_k / (FRAME_INTERVAL_S * (len(sequence.frames) - 1))
    scene = hot_part_scene(case.peak_c, hot_optics(case.projector, case.band_pass), cooling_rate=cooling)
    options = SimulationOptions(camera_effects=CameraEffects(blur_sigma=0.5),
                                projector_effects=ProjectorEffects(blur_sigma=0.5), seed=seed,
                                frame_interval_s=FRAME_INTERVAL_S,
                                thermal_effects=ThermalEffects(supersample=1))  # not scored here
    simulated = SimulatedStation(rig, scene, scene.temperature, options)
    station = Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=0.0)
    capture = station.capture(sequence, patterns,
                              exposure=ExposureControl(mode=case.exposure, hdr_repeats=case.hdr_repeats))
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    scan = reconstruct_scan(capture.frames, sequence, camera, projector,
                            saturation_level=capture.exposure["saturation_level"],
                            glow_window_px=GLOW_WINDOW_SIGMA_PX if case.window else 0.0)
    truth = simulated.view().truth
    cloud = scan.cloud
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float64)
    error = np.linalg.norm(points - truth.points[v, u], axis=1)
    has_point = np.zeros(truth.surface.shape, dtype=bool)
    has_point[v, u] = True
    interior = _interior(truth.surface) & truth.lit
    on_part = np.isin(truth.surface, PART_SURFACES)
    part_pixels, fixture_pixels = interior & on_part, interior & (truth.surface == FIXTURE_SURFACE)
    part_points = on_part[v, u]
    interior_part_points = part_pixels[v, u]
    depth = np.full(truth.surface.shape, np.nan, dtype=np.float32)
    depth[v, u] = points @ camera.R[2] + camera.t[2]
    return Result(
        case=case,
        exposures_us=capture.exposure["exposures_us"],
        glow_level=capture.exposure["glow_level"],
        part_reconstructed=float(has_point[part_pixels].mean()),
        fixture_reconstructed=float(has_point[fixture_pixels].mean()),
        part_mean_error_mm=float(error[interior_part_points].mean()) if interior_part_points.any() else float("nan"),
        part_off_1mm=float((error[part_points] > 1.0).mean()) if part_points.any() else 0.0,
        scan=scan,
        frames=capture.frames,
        depth_map=depth,
    )


def _bracket(exposures_us: list[float]) -> str:
    """The exposures filmed, the repeated shortest one as ``N x``."""
    repeats = exposures_us.count(exposures_us[0])
    first = f"{repeats} x {exposures_us[0]:.0f}" if repeats > 1 else f"{exposures_us[0]:.0f}"
    return " + ".join([first] + [f"{e:.0f}" for e in exposures_us[repeats:]])


def _row(result: Result) -> str:
    glow = result.scan.glow
    hint = glow.hint if glow is not None and glow.hint else "-"
    lost = 0.0 if glow is None else glow.saturated_fraction + glow.lost_fraction
    return (f"| {result.case.name} | {_bracket(result.exposures_us)} | {100 * result.glow_level:.1f} % | "
            f"{100 * result.part_reconstructed:.2f} % | {100 * result.fixture_reconstructed:.2f} % | "
            f"{result.part_mean_error_mm:.4f} | {100 * result.part_off_1mm:.3f} % | "
            f"{100 * lost:.1f} % | {hint} |")


def _ablation_row(result: Result) -> str:
    return (f"| {_bracket(result.exposures_us)} | {'on' if result.case.window else 'off'} | "
            f"{100 * result.part_reconstructed:.2f} % | {100 * result.fixture_reconstructed:.2f} % | "
            f"{result.part_mean_error_mm:.4f} | {100 * result.part_off_1mm:.3f} % |")


def table(results: list[Result], scale: float) -> str:
    lines = [f"Camera scale {scale:g} ({round(1280 * scale)} x {round(800 * scale)} px).", "",
             "| case | exposure us | glow (p99, of full scale) | part reconstructed | fixture reconstructed | "
             "part mean error mm | part points off > 1 mm | glowing pixels lost (scan result) | hint |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += [_row(result) for result in results]
    return "\n".join(lines) + "\n"


def figure(result: Result, path: Path) -> None:
    """A glowing part's white, phase and black frames next to its reconstruction's depth map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    saturation = 4095.0
    panels = [(result.frames[0], "white frame"), (result.frames[20], "phase frame"),
              (result.frames[1], "black frame: the glow")]
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.2))
    for ax, (image, title) in zip(axes, panels):
        ax.imshow(image, cmap="gray", vmin=0, vmax=saturation)
        ax.set_title(title)
        ax.axis("off")
    shown = axes[3].imshow(result.depth_map, cmap="viridis")
    axes[3].set_title("reconstruction: depth mm")
    axes[3].axis("off")
    fig.colorbar(shown, ax=axes[3], fraction=0.046)
    fig.suptitle(result.case.name)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--figure", type=Path, default=None)
    parser.add_argument("--ablation", action="store_true",
                        help="only white 1000 C HDR, with 1, 4 or 8 films of the short exposure, the window on or off")
    args = parser.parse_args()
    if args.ablation:
        print("| HDR bracket, us | windowed decoding | part | fixture | part mean error mm | part points off > 1 mm |")
        print("|---|---|---|---|---|---|")
        for case in ABLATION:
            print(_ablation_row(run_case(case, args.scale)), flush=True)
        return
    print(ratio_table())
    results = []
    for case in CASES:
        result = run_case(case, args.scale)
        print(_row(result), flush=True)
        results.append(result)
    print()
    print(table(results, args.scale))
    if args.figure is not None:
        figure(next(r for r in results if r.case.name == "white, 1000 C, auto"), args.figure)


if __name__ == "__main__":
    main()
