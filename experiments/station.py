"""The simulated four-head station (issue 36): coverage, merge residuals, point and temperature errors, pictures.

Run (about 1.5 minutes at full resolution on this 2-core machine):

    nice -n 5 .venv/bin/python experiments/station.py --out docs/figures/station

Data: own simulated station only (``services.simulation.station``: ``presets.station_rig`` around the
300 x 90 mm carbon-steel shaft at 1000 degC with a 0.3 mm dent on the side away from the first head;
nothing here was tuned on other data, and no threshold was chosen on this run). Two runs of the same
frames:

- **calibrated**: the heads reconstructed with the true rig (a perfect station calibration);
- **calibration off by 1 sigma**: heads 2..4 each moved, as a whole, by a rigid motion of 0.05 mm and
  0.01 deg (the station calibration's target uncertainty) in random directions (seeded), so that
  the merge's pose refinement has something to undo; head 1 is the reference.

Per run: the lateral coverage (share of 2 mm cells of the hot shaft's side holding a point), the
overlap residual of each head pair before and after the refinement (RMS over 4 mm patches of the
mean distance along the normal: the misregistration; and per point, with the noise), the pose
corrections, each head's point error (distance from the true hot surface: median, p95, worst),
and, for the calibrated run, the temperature error of the fused field against the true surface
temperature (median, p95, worst) and the share of points given a temperature; then the calibrated
run's field inspected against the nominal shaft: cold diameter, length, ovality, the dent's depth and the
verdict. ``experiments/station_parts.py`` makes the distribution over twenty shafts.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from services.formats.part import load_part  # noqa: E402
from services.formats.rig import Rig  # noqa: E402
from services.formats.station_capture import read_station_capture, thermal_path  # noqa: E402
from services.formats.thermal import read_thermal_frame  # noqa: E402
from services.geometry.camera_model import CameraModel  # noqa: E402
from services.inspection.inspect import inspect_field, prepare_part  # noqa: E402
from services.open3d_loader import open3d  # noqa: E402
from services.pipeline.field import fuse_field  # noqa: E402
from services.pipeline.station import MergedCloud, reconstruct_station  # noqa: E402
from services.pipeline.tables import TriangulationTables  # noqa: E402
from services.simulation.hot_part import write_shaft_part  # noqa: E402
from services.simulation.station import StationScene, film_station, lateral_coverage, station_scene  # noqa: E402

HEAD_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b")


def moved_rig(rig: Rig, seed: int, translation_mm: float, rotation_deg: float) -> tuple[Rig, dict[str, np.ndarray]]:
    """The rig with every head but the first moved as a whole by a rigid motion of the given sizes in random
    directions; the motions (4x4, world to world) by head."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    devices = dict(rig.devices)
    motions = {}
    for head in rig.heads[1:]:
        axis, direction = rng.normal(size=3), rng.normal(size=3)
        rotation = Rotation.from_rotvec(np.radians(rotation_deg) * axis / np.linalg.norm(axis)).as_matrix()
        # about the head's camera centre: the head's devices turn together
        centre = rig.devices[head.camera].centre
        translation = translation_mm * direction / np.linalg.norm(direction) + centre - rotation @ centre
        motion = np.eye(4)
        motion[:3, :3], motion[:3, 3] = rotation, translation
        motions[head.name] = motion
        for name in (head.camera, head.projector):
            device = rig.devices[name]
            R = device.R @ rotation.T
            devices[name] = CameraModel(kind=device.kind, width=device.width, height=device.height, K=device.K,
                                        dist=device.dist, R=R, t=device.t - R @ translation)
    return Rig(devices, rig.units, rig.station_heads), motions


def surface_distance(points: np.ndarray, station: StationScene) -> np.ndarray:
    o3d = open3d()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(station.part.to_world(station.part.hot_vertices_part()).astype(np.float32)),
                        o3d.core.Tensor(station.part.triangles.astype(np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, dtype=np.float32))).numpy()


def stats(values: np.ndarray) -> str:
    values = np.asarray(values)
    if not len(values):
        return "-"
    return f"{np.median(values):.3f} / {np.percentile(values, 95):.3f} / {values.max():.3f}"


def merge_rows(merged: MergedCloud, station: StationScene) -> list[str]:
    report = merged.report
    cloud = merged.cloud
    distance = surface_distance(cloud.points, station)
    rows = [f"| lateral surface covered (2 mm cells) | {lateral_coverage(cloud.points, station):.1%} |",
            f"| points measured / kept after thinning | {sum(report.measured_points)} / {sum(report.kept_points)} |"]
    for before, after in zip(report.residuals_before, report.residuals):
        rows.append(f"| overlap {after.first}/{after.second}: residual before -> after merge, mm RMS over 4 mm "
                    f"patches (per point) | {before.patch_rms_mm:.4f} ({before.rms_mm:.4f}) -> "
                    f"**{after.patch_rms_mm:.4f}** ({after.rms_mm:.4f}), {after.points} points |")
    for correction in report.corrections[1:]:
        state = "applied" if correction.applied else f"refused: {correction.reason}"
        rows.append(f"| pose correction of {correction.head} | {correction.translation_mm:.3f} mm, "
                    f"{correction.rotation_deg:.4f} deg ({state}) |")
    for index, name in enumerate(report.heads):
        rows.append(f"| point error of {name}, mm (median / p95 / worst) | "
                    f"{stats(distance[cloud['head'] == index])} |")
    return rows


def inspection_rows(field, station: StationScene) -> list[str]:
    """The calibrated run's field inspected against the nominal shaft; each measure against the truth."""
    with tempfile.TemporaryDirectory() as directory:
        prepared = prepare_part(load_part(write_shaft_part(Path(directory), station.truth.diameter_mm,
                                                           station.truth.length_mm)))
    started = time.perf_counter()
    report = inspect_field(field=field, part=prepared).report
    elapsed = time.perf_counter() - started
    features = {item["name"]: item for item in report["features"]}
    rows = ["", "| target (inspection of the calibrated run's field) | truth | measured (U) | error | result |",
            "|---|---|---|---|---|"]
    for name, truth, target in (("body_diameter", station.truth.diameter_mm, 0.05),
                                ("length", station.truth.length_mm, 0.1)):
        item = features[name]
        error = item["cold"] - truth
        result = "met" if abs(error) <= target else "**not met**"
        rows.append(f"| cold {name.replace('body_', '')} within +-{target} mm | {truth:.3f} | {item['cold']:.3f} "
                    f"({item['uncertainty']:.3f}) | {error:+.3f} | {result} |")
    ovality = features["body_ovality"]
    rows.append(f"| ovality (truth 0, round) | 0 | {ovality['cold']:.3f} ({ovality['uncertainty']:.3f}) | "
                f"{ovality['cold']:+.3f} | |")
    dents = [d for d in report["surface"]["defects"] if d["depth"] < 0]
    if station.truth.dent is not None:
        depth = -station.truth.dent.height_mm
        if dents:
            found = min(dents, key=lambda d: d["depth"])
            error = -found["depth"] - depth
            rows.append(f"| dent of {depth:g} mm found, depth within +-0.05 mm | {depth:.3f} | "
                        f"{-found['depth']:.3f} | {error:+.3f} | {'met' if abs(error) <= 0.05 else '**not met**'} |")
        else:
            rows.append(f"| dent of {depth:g} mm found, depth within +-0.05 mm | {depth:.3f} | not found | | "
                        "**not met** |")
    others = len(report["surface"]["defects"]) - min(len(dents), 1)
    rows.append(f"| other surface defects listed (none in the truth) | 0 | {others} | | |")
    rows.append(f"| verdict | | {report['verdict']} | | inspect {elapsed:.1f} s |")
    return rows


def render_pictures(field, station: StationScene, out: Path) -> None:
    """The merged field unrolled (position along the axis against the angle round it) and seen in perspective,
    coloured by head and by temperature."""
    points = field.points
    rng = np.random.default_rng(0)
    sample = rng.permutation(len(points))[:60_000]
    p, head, temperature = points[sample], np.asarray(field["head"])[sample], np.asarray(field["temperature"])[sample]
    angle = np.degrees(np.arctan2(p[:, 2], -p[:, 1]))  # 0 at the top (the first head), round toward +z
    figure = plt.figure(figsize=(10.0, 6.4))
    colours = np.array(HEAD_COLOURS)[head % len(HEAD_COLOURS)]
    seen = np.isfinite(temperature)
    for column, (title, colour) in enumerate((("by head", None), ("by temperature", "temperature"))):
        axes = figure.add_subplot(2, 2, column + 1, projection="3d")
        if colour is None:
            axes.scatter(p[:, 0], p[:, 2], -p[:, 1], c=colours, s=0.3, linewidths=0)
        else:
            axes.scatter(p[~seen, 0], p[~seen, 2], -p[~seen, 1], c="0.75", s=0.3, linewidths=0)
            shown = axes.scatter(p[seen, 0], p[seen, 2], -p[seen, 1], c=temperature[seen], cmap="inferno", s=0.3,
                                 linewidths=0)
        axes.set_box_aspect((300, 100, 100))
        axes.view_init(elev=25, azim=-60)
        axes.set_axis_off()
        axes.set_title(f"merged field, {title}")
        flat = figure.add_subplot(2, 2, column + 3)
        if colour is None:
            flat.scatter(p[:, 0], angle, c=colours, s=0.2, linewidths=0)
            for index, name in enumerate(station.rig.heads):
                flat.scatter([], [], c=HEAD_COLOURS[index], s=12, label=name.name)
            flat.legend(loc="upper right", fontsize=7, markerscale=1.5, ncol=2)
        else:
            flat.scatter(p[~seen, 0], angle[~seen], c="0.75", s=0.2, linewidths=0)
            flat.scatter(p[seen, 0], angle[seen], c=temperature[seen], cmap="inferno", s=0.2, linewidths=0)
            figure.colorbar(shown, ax=flat, label="°C (grey: no thermal camera sees it)")
        flat.set_xlabel("along the axis, mm")
        flat.set_ylabel("round the axis, deg (0: top)")
        flat.set_title("unrolled (end faces at the ends)")
    figure.tight_layout()
    figure.savefig(out / "station_field.png", dpi=90)
    plt.close(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "station")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--dent", type=float, default=0.3, help="dent depth, mm (default 0.3)")
    parser.add_argument("--capture", type=Path, default=None,
                        help="keep the filmed station capture here, and read it from here when it is there")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    station = station_scene(scale=args.scale, dent_depth_mm=args.dent)
    if args.capture is not None and (args.capture / "thermal").is_dir():
        heads = read_station_capture(args.capture, station.rig)
        thermal = {name: read_thermal_frame(thermal_path(args.capture, name))
                   for name, device in station.rig.devices.items() if device.kind == "thermal"}
    else:
        capture = film_station(station, seed=args.seed)
        print(f"filmed {len(capture.heads)} heads in {time.perf_counter() - started:.0f} s", file=sys.stderr)
        heads, thermal = tuple(shot.capture for shot in capture.heads), dict(capture.thermal)
        if args.capture is not None:
            capture.save(args.capture)
    tables = TriangulationTables()

    lines = [f"Own simulated station, scale {args.scale:g}, seed {args.seed}, dent {args.dent:g} mm; "
             f"`.venv/bin/python experiments/station.py{'' if args.scale == 1 else f' --scale {args.scale:g}'}`", ""]
    runs = (("calibrated", station.rig), ("calibration off by 1 sigma (0.05 mm, 0.01 deg)",
                                          moved_rig(station.rig, args.seed + 1, 0.05, 0.01)[0]))
    field = None
    for title, rig in runs:
        began = time.perf_counter()
        merged = reconstruct_station(heads=heads, rig=rig, tables=tables)
        # the rig's thermal cameras are the true ones in both runs (the motion moved only the heads)
        lines += [f"**{title}**", "", "| quantity | value |", "|---|---|", *merge_rows(merged, station)]
        if field is None:
            field = fuse_field(cloud=merged.cloud, rig=rig, thermal=list(thermal.items()))
            temperature = field["temperature"]
            seen = np.isfinite(temperature)
            error = np.abs(temperature[seen] - station.part.surface_temperature(field.points[seen]))
            lines += [f"| points with a temperature (two thermal cameras) | {seen.mean():.1%} |",
                      f"| temperature error, K (median / p95 / worst) | {stats(error)} |"]
        lines += [f"| reconstruct 4 heads + merge, this process (not a benchmark) | "
                  f"{time.perf_counter() - began:.1f} s |", ""]
    lines += inspection_rows(field, station)
    render_pictures(field, station, args.out)
    print("\n".join(lines))
    print(f"done in {time.perf_counter() - started:.0f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
