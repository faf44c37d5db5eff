"""Wrong points at projector shadows and under a hot part's glow: issue 34's tuning scene, scored against
the simulator's ground truth (docs/structured-light.md, "Points at projector shadows").

Run: ``nice -n 10 .venv/bin/python experiments/shadow_scene.py [--scale S] [--cases cold,blue1200,white1250]``
(full size: about a minute per case on 2 cores); ``--zoo 1000-1015`` reconstructs zoo scenes instead
(``zoo_points``: reconstruction alone, scored as experiments/zoo.py scores it).

The scene (``shadow_scene``): a capped cylinder (r 40 mm, 160 mm long, vertical) and a sphere (r 60 mm)
before a plate tilted 25 degrees about the vertical, 720..800 mm from the rig; the rig (``shadow_rig``): a
1024x768 projector (f 1150 px) at the origin and a 1280x800 camera (f 1400 px, mild distortion) 260 mm to
its side, both aimed at (0, 0, 650). The parts cast projector shadows on the plate that the camera sees.
Frames are the project's own patterns (complementary Gray code + 12-step phase shift). Three cases:

- ``cold``: the cold simulator, camera blur 0.7 px, projector blur 0.8 px, noise 1.5 grey levels, 8 bits;
- ``blue1200``: the parts at 1200 C, blue projector and a 450/40 nm filter, 12 bits, automatic exposure;
- ``white1250``: the parts at 1250 C under the unfiltered white projector, automatic exposure.

A point is wrong when it lies more than 1 mm from the true surface point of its pixel's centre.
Coverage is the share of the pixels lit by the projector and seen by the camera, whose 4-neighbours see
the same surface, that have a point. This scene was used to tune the decoder's shadow test
(``decode.SHADOW_CONTRAST``); it is a tuning scene, not a held-out figure.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import numpy as np

from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.simulation.render import CameraEffects, ProjectorEffects, render_frames, render_view
from services.structured_light.patterns import generate_sequence
from services.structured_light.reconstruct import reconstruct_scan

PART_SURFACES = (0, 1)
PLATE_SURFACE = 2
FRAME_INTERVAL_S = 1 / 30


@dataclass(frozen=True)
class Score:
    case: str
    points: int
    wrong: int  # points more than 1 mm from the truth
    wrong_on_plate: int
    coverage: float  # of the lit, seen interior pixels
    part_coverage: float
    glow_hint: str | None

    @property
    def wrong_fraction(self) -> float:
        return self.wrong / max(self.points, 1)


def _interior(surface: np.ndarray) -> np.ndarray:
    inside = np.zeros(surface.shape, bool)
    inside[1:-1, 1:-1] = True
    for axis, shift in ((0, 1), (0, -1), (1, 1), (1, -1)):
        inside &= np.roll(surface, shift, axis=axis) == surface
    return inside


def capture(case: str, scale: float = 1.0, seed: int = 0):
    """The frames, sequence, saturation level and ground truth of one case."""
    from services.simulation.presets import shadow_rig, shadow_scene

    rig = shadow_rig(scale)
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    if case == "cold":
        sequence, patterns = generate_sequence(projector.width, projector.height)
        view = render_view(shadow_scene(), camera, projector)
        frames = render_frames(view, patterns, np.random.default_rng(seed),
                               CameraEffects(exposure=0.8, blur_sigma=0.7, noise_sigma=1.5),
                               ProjectorEffects(blur_sigma=0.8))
        return rig, sequence, frames, None, view.truth
    from device_gateway.drivers.simulated import SimulatedStation, SimulationOptions
    from device_gateway.station import ExposureControl, Station
    from services.simulation.thermal import ThermalEffects

    peak, light, band = {"blue1200": (1200.0, "blue", (450.0, 40.0)), "white1250": (1250.0, "white", None),
                         "white1000": (1000.0, "white", None)}[case]
    scene = shadow_scene(peak, light, band)
    sequence, patterns = generate_sequence(projector.width, projector.height, closing_black=True)
    options = SimulationOptions(camera_effects=CameraEffects(blur_sigma=0.7),
                                projector_effects=ProjectorEffects(blur_sigma=0.8), seed=seed,
                                frame_interval_s=FRAME_INTERVAL_S, thermal_effects=ThermalEffects(supersample=1))
    rig_with_thermal = Rig(devices={**rig.devices, "thermal": CameraModel(
        kind="thermal", width=160, height=128, K=[[190.0, 0, 79.5], [0, 190.0, 63.5], [0, 0, 1]], dist=[],
        R=np.eye(3).tolist(), t=[0.0, 0.0, 0.0])})
    simulated = SimulatedStation(rig_with_thermal, scene, scene.temperature, options)
    station = Station(simulated.camera, simulated.thermal, simulated.projector, settle_s=0.0)
    captured = station.capture(sequence, patterns, exposure=ExposureControl(mode="auto"))
    return rig, sequence, captured.frames, captured.exposure["saturation_level"], simulated.view().truth


def score(case: str, scale: float = 1.0, seed: int = 0) -> Score:
    rig, sequence, frames, saturation, truth = capture(case, scale, seed)
    camera, projector = rig.devices["camera"], rig.devices["projector"]
    scan = reconstruct_scan(frames, sequence, camera, projector, saturation_level=saturation)
    cloud = scan.cloud
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float64)
    error = np.linalg.norm(points - truth.points[v, u], axis=1)
    error[~np.isfinite(error)] = np.inf  # a point where the camera sees nothing
    wrong = error > 1.0
    has_point = np.zeros(truth.surface.shape, bool)
    has_point[v, u] = True
    counted = _interior(truth.surface) & truth.lit & (truth.surface >= 0)
    part = counted & np.isin(truth.surface, PART_SURFACES)
    return Score(case=case, points=len(error), wrong=int(wrong.sum()),
                 wrong_on_plate=int((wrong & (truth.surface[v, u] == PLATE_SURFACE)).sum()),
                 coverage=float(has_point[counted].mean()),
                 part_coverage=float(has_point[part].mean()) if part.any() else float("nan"),
                 glow_hint=None if scan.glow is None else scan.glow.hint)


def zoo_points(seed: int) -> dict:
    """Reconstruction alone of zoo scene ``seed`` (services/simulation/zoo.py), scored as experiments/zoo.py
    scores it: wrong points (> 1 mm from the truth at the pixel centre) and the coverage of the pixels lit and
    seen whose 8-neighbours are lit and see the same surface."""
    from services.errors import InputError
    from zoo import film_zoo_scene
    from services.pipeline.reconstruct import reconstruct_capture
    from services.pipeline.tables import TriangulationTables
    from services.simulation.zoo import zoo_scene

    zoo = zoo_scene(seed)
    rig = zoo.rig
    sequence, capture, simulated = film_zoo_scene(zoo, seed)  # experiments/zoo.py, beside this script
    truth = simulated.view().truth
    result = {"seed": seed, "kind": zoo.kind}
    try:
        cloud = reconstruct_capture(frames=capture.frames, sequence=sequence, rig=rig, tables=TriangulationTables(),
                                    saturation_level=capture.exposure["saturation_level"]).cloud
    except InputError as error:
        return {**result, "refused": str(error), "points": 0, "wrong": 0, "coverage": 0.0}
    u, v = np.rint(cloud["u"]).astype(int), np.rint(cloud["v"]).astype(int)
    error = np.linalg.norm(cloud.points - truth.points[v, u], axis=1)
    wrong = ~(error <= 1.0)  # NaN: the pixel's centre ray meets nothing
    same = truth.lit & (truth.surface >= 0)  # lit pixels whose 8-neighbours are lit and see the same surface
    same[[0, -1], :] = same[:, [0, -1]] = False
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                shifted = np.roll(np.roll(truth.surface, dy, axis=0), dx, axis=1)
                same &= (shifted == truth.surface) & np.roll(np.roll(truth.lit, dy, axis=0), dx, axis=1)
    has_point = np.zeros(truth.surface.shape, bool)
    has_point[v, u] = True
    return {**result, "points": int(len(error)), "wrong": int(wrong.sum()),
            "coverage": float(has_point[same].mean()) if same.any() else float("nan")}


def zoo_table(seeds: list[int]) -> str:
    rows = []
    lines = ["| seed | part | points | off > 1 mm | coverage |", "|---|---|---|---|---|"]
    for seed in seeds:
        row = zoo_points(seed)
        rows.append(row)
        rate = row["wrong"] / max(row["points"], 1)
        lines.append(f"| {seed} | {row['kind']} | {row['points']} | {100 * rate:.3f} % | {100 * row['coverage']:.2f} % |")
        print(lines[-1], flush=True)
    rates = [r["wrong"] / max(r["points"], 1) for r in rows]
    coverage = [r["coverage"] for r in rows]
    lines.append(f"| {len(rows)} scenes | | | median {100 * np.median(rates):.3f} %, 95th percentile "
                 f"{100 * np.percentile(rates, 95):.3f} %, worst {100 * max(rates):.3f} % | median "
                 f"{100 * np.median(coverage):.2f} %, 5th percentile {100 * np.percentile(coverage, 5):.2f} % |")
    return "\n".join(lines) + "\n"


def _seeds(text: str) -> list[int]:
    seeds = []
    for part in text.split(","):
        first, _, last = part.partition("-")
        seeds.extend(range(int(first), int(last or first) + 1))
    return seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--cases", default="cold,blue1200,white1250")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--zoo", help="instead, reconstruct zoo scenes (seeds: 1000-1015,1020) and score the points")
    args = parser.parse_args()
    if args.zoo:
        print(zoo_table(_seeds(args.zoo)))
        return
    print("| case | points | off > 1 mm | of them on the plate | coverage of lit, seen pixels | of the parts | hint |")
    print("|---|---|---|---|---|---|---|")
    for case in args.cases.split(","):
        s = score(case, args.scale, args.seed)
        print(f"| {case} | {s.points} | {s.wrong} ({100 * s.wrong_fraction:.3f} %) | {s.wrong_on_plate} | "
              f"{100 * s.coverage:.2f} % | {100 * s.part_coverage:.2f} % | {s.glow_hint or '-'} |", flush=True)


if __name__ == "__main__":
    main()
