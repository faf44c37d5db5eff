"""Twenty shafts through the simulated four-head station, end to end: the distribution over parts (issue 36).

Run (about a minute a part at full resolution on this 2-core machine, idle):

    OPENBLAS_NUM_THREADS=1 nice -n 5 .venv/bin/python experiments/station_parts.py --seeds 300-319 \\
        --json docs/figures/station/station-parts.json --markdown docs/station.md

Data: own simulated station (``services.simulation.station``), seeds 300..319, none of them used to choose a
threshold or a default (the station's code and the inspection's rules were fixed before this script ran;
``experiments/station.py`` is one scene, seed 0). Per seed, one shaft made off its nominal 90 x 300 mm
(carbon steel, drawn at 950..1100 degC at its centre), even seeds in tolerance, odd seeds out:

- in tolerance: diameter within +-0.4 of its tolerance (+-0.3 mm), length within +-0.4 of its (+-1 mm), and
  a dent of 0.1..0.5 mm on the side away from the first head (the surface tolerance is +-1 mm);
- out of tolerance, by turns: the diameter 1.5..3 tolerances off, the length 1.5..3 tolerances off, or a
  dent of 1.3..2.5 mm.

The station films it (``film_station``, the seed's noise), its heads are reconstructed with a calibration
off by one sigma of the station calibration's target (heads 2..4 moved by 0.05 mm and 0.01 deg in the seed's
random directions, as ``experiments/station.py``'s second run), merged, fused from both thermal cameras
and inspected against the nominal shaft (``hot_part.write_shaft_part``): what ``thermofield reconstruct``,
``field`` and ``inspect`` do with a station capture. Each part is scored against its truth.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.station import moved_rig, surface_distance  # noqa: E402
from services.formats.part import load_part  # noqa: E402
from services.inspection.inspect import inspect_field, prepare_part  # noqa: E402
from services.pipeline.field import fuse_field  # noqa: E402
from services.pipeline.station import reconstruct_station  # noqa: E402
from services.pipeline.tables import TriangulationTables  # noqa: E402
from services.simulation.hot_part import write_shaft_part  # noqa: E402
from services.simulation.station import film_station, lateral_coverage, station_scene  # noqa: E402

NOMINAL = {"diameter": 90.0, "length": 300.0}
TOLERANCE = {"diameter": 0.3, "length": 1.0, "surface": 1.0}
TARGETS = {"diameter": 0.05, "length": 0.1, "dent": 0.05}
END_FACE_MARGIN_MM = 10.0
TABLE_BEGIN, TABLE_END = "<!-- station-parts:begin -->", "<!-- station-parts:end -->"


def draw_part(seed: int) -> dict:
    """The seed's shaft: in tolerance on even seeds, out on odd ones (by turns its diameter, length or a dent)."""
    rng = np.random.default_rng([36, seed])
    inside = seed % 2 == 0

    def off(name: str, out: bool) -> float:
        share = rng.uniform(1.5, 3.0) if out else rng.uniform(-0.4, 0.4)
        return float(share * TOLERANCE[name] * (rng.choice([-1.0, 1.0]) if out else 1.0))

    defect = None if inside else ("diameter", "length", "dent")[(seed // 2) % 3]
    return {"seed": seed, "in_tolerance": inside, "defect": defect,
            "diameter": NOMINAL["diameter"] + off("diameter", defect == "diameter"),
            "length": NOMINAL["length"] + off("length", defect == "length"),
            "dent": float(rng.uniform(1.3, 2.5) if defect == "dent" else rng.uniform(0.1, 0.5)),
            "temperature": float(rng.uniform(950.0, 1100.0))}


def run_part(seed: int, scale: float, nominal_part) -> dict:
    drawn = draw_part(seed)
    started = time.perf_counter()
    station = station_scene(scale=scale, dent_depth_mm=drawn["dent"], temperature_c=drawn["temperature"],
                            diameter_mm=drawn["diameter"], length_mm=drawn["length"])
    capture = film_station(station, seed=seed)
    rig, _ = moved_rig(station.rig, seed + 1, 0.05, 0.01)
    merged = reconstruct_station(heads=tuple(shot.capture for shot in capture.heads), rig=rig,
                                 tables=TriangulationTables())
    field = fuse_field(cloud=merged.cloud, rig=rig, thermal=list(capture.thermal.items()))
    report = inspect_field(field=field, part=nominal_part).report
    features = {item["name"]: item for item in report["features"]}
    # the drawn dent lies on the side, 40 mm from the middle: an end face (a part of another length) is not it
    dents = [defect for defect in report["surface"]["defects"] if defect["depth"] < 0
             and abs(defect["center"][0]) <= NOMINAL["length"] / 2 - END_FACE_MARGIN_MM]
    deepest = min(dents, key=lambda defect: defect["depth"]) if dents else None
    residuals = [residual.patch_rms_mm for residual in merged.report.residuals]
    distance = surface_distance(merged.cloud.points, station)
    return {**drawn, "verdict": report["verdict"],
            "coverage": lateral_coverage(merged.cloud.points, station),
            "overlap_residual_max_mm": max(residuals),
            "point_error_p95_mm": float(np.percentile(distance, 95)),
            "diameter_error": features["body_diameter"]["cold"] - drawn["diameter"],
            "diameter_uncertainty": features["body_diameter"]["uncertainty"],
            "diameter_verdict": features["body_diameter"]["verdict"],
            "length_error": features["length"]["cold"] - drawn["length"],
            "length_uncertainty": features["length"]["uncertainty"],
            "length_verdict": features["length"]["verdict"],
            "defects": [{"center": [round(c, 2) for c in defect["center"]], "depth": defect["depth"]}
                        for defect in report["surface"]["defects"]],
            "dent_found": deepest is not None,
            "dent_deviation": None if deepest is None else deepest["depth"],
            "other_defects": len(report["surface"]["defects"]) - (1 if deepest is not None else 0),
            "end_face_defects": sum(abs(defect["center"][0]) > NOMINAL["length"] / 2 - END_FACE_MARGIN_MM
                                    for defect in report["surface"]["defects"]),
            "surface_verdict": report["surface"]["verdict"],
            "not_ok": [f"{name} {item['verdict']}" for name, item in features.items() if item["verdict"] != "OK"],
            "seconds": round(time.perf_counter() - started, 1)}


def dent_error(row: dict) -> float | None:
    """The deepest dent's deviation from the nominal surface less the truth's there: the true radius's offset
    from the nominal less the dent's depth (mm)."""
    deviation = row.get("dent_deviation")
    if deviation is None and row.get("dent_error") is not None:  # rows of a run before this field was kept
        deviation = -(row["dent_error"] + row["dent"])
    if deviation is None:
        return None
    return deviation - ((row["diameter"] - NOMINAL["diameter"]) / 2 - row["dent"])


def _stats(values) -> str:
    values = np.abs(np.asarray([v for v in values if v is not None], dtype=np.float64))
    if not len(values):
        return "-"
    return f"{np.median(values):.3f} / {np.percentile(values, 95):.3f} / {values.max():.3f}"


def _covered(rows: list[dict]) -> str:
    covered = 100 * np.asarray([row["coverage"] for row in rows])
    return f"{np.median(covered):.1f} / {np.percentile(covered, 5):.1f} / {covered.min():.1f}"


def summarise(rows: list[dict], command: str) -> str:
    seeds = [row["seed"] for row in rows]
    inside = [row for row in rows if row["in_tolerance"]]
    outside = [row for row in rows if not row["in_tolerance"]]
    lines = [f"Own simulated station, held out: seeds {min(seeds)}..{max(seeds)} ({len(rows)} shafts, "
             f"{len(inside)} in and {len(outside)} out of tolerance), calibration off by 1 sigma; `{command}`", "",
             "| measure (every part) | median / 95th percentile / worst | target |", "|---|---|---|",
             f"| lateral surface covered, % (median / 5th percentile / lowest) | {_covered(rows)} | >= 95 % |",
             f"| overlap residual after the merge, worst pair, mm | {_stats([row['overlap_residual_max_mm'] for row in rows])} | 0.03 |",
             f"| point error, 95th percentile of the part's points, mm | {_stats([row['point_error_p95_mm'] for row in rows])} | |",
             f"| cold diameter error, mm | {_stats([row['diameter_error'] for row in rows])} | 0.05 |",
             f"| cold length error, mm | {_stats([row['length_error'] for row in rows])} | 0.1 |",
             f"| dent depth error, mm ({sum(row['dent_found'] for row in rows)} of {len(rows)} dents found) | "
             f"{_stats([dent_error(row) for row in rows])} | 0.05 |",
             f"| other surface defects listed (the truth's: its end faces, half its length's deviation off) | "
             f"{_stats([row['other_defects'] for row in rows])} | |", "",
             "| truth | OK | NotOK | NotDecidable |", "|---|---|---|---|"]
    for title, group in (("in tolerance", inside), ("out of tolerance", outside)):
        counts = [sum(row["verdict"] == verdict for row in group) for verdict in ("OK", "NotOK", "NotDecidable")]
        lines.append(f"| {title} ({len(group)}) | {' | '.join(str(count) for count in counts)} |")
    wrong = [row for row in rows if row["verdict"] != ("OK" if row["in_tolerance"] else "NotOK")]
    lines += ["", "Parts not judged as their truth: " + (", ".join(
        f"seed {row['seed']} ({'in' if row['in_tolerance'] else 'out: ' + row['defect']}, {row['verdict']}; "
        f"surface {row['surface_verdict']}; features not OK: {', '.join(row['not_ok']) or 'none'})"
        for row in wrong) or "none") + "."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", default="300-319", help="seeds and ranges, e.g. 300-319")
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--json", type=Path, required=True, help="per-part results, rewritten after every part")
    parser.add_argument("--markdown", type=Path, help="write the table between its markers in this file")
    parser.add_argument("--summarise", action="store_true", help="run nothing: tabulate --json")
    args = parser.parse_args()
    seeds = [seed for part in args.seeds.split(",") for seed in
             (range(int(part.split("-")[0]), int(part.split("-")[1]) + 1) if "-" in part else [int(part)])]
    rows = {row["seed"]: row for row in json.loads(args.json.read_text())} if args.json.exists() else {}
    if not args.summarise:
        with tempfile.TemporaryDirectory() as directory:
            nominal = prepare_part(load_part(write_shaft_part(Path(directory), NOMINAL["diameter"],
                                                              NOMINAL["length"])))
        for seed in seeds:
            if seed in rows:
                continue
            rows[seed] = run_part(seed, args.scale, nominal)
            print(json.dumps({**{key: rows[seed][key] for key in ("seed", "defect", "verdict", "diameter_error",
                                                                   "length_error", "seconds")},
                              "dent_error": dent_error(rows[seed])}), flush=True)
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(sorted(rows.values(), key=lambda row: row["seed"]), indent=1))
    done = [rows[seed] for seed in seeds if seed in rows]
    command = f".venv/bin/python experiments/station_parts.py --seeds {args.seeds}" + \
        ("" if args.scale == 1 else f" --scale {args.scale:g}")
    table = summarise(done, command)
    print(table)
    if args.markdown is not None:
        text = args.markdown.read_text()
        begin, end = text.index(TABLE_BEGIN) + len(TABLE_BEGIN), text.index(TABLE_END)
        args.markdown.write_text(text[:begin] + "\n" + table + "\n" + text[end:])


if __name__ == "__main__":
    main()
