"""Inspection all round (issue 36): a shaft seen by the four heads of a station, as a merged field (the table
of docs/inspection.md, "All round").

Run: nice .venv/bin/python experiments/allround_inspection.py [--scans 100-109] [--parts 200-219]

The data are simulated all-round clouds (``hot_part.all_round_field``): points sampled on the hot
carbon-steel shaft (``hot_part.hot_shaft``, nominal 90 mm x 300 mm, ``write_shaft_part``) at 4 points per
mm^2, each measured by the best-placed of four heads (``station_heads``) with 0.02 mm structured-light
noise along its line of sight, 50 mK NETD and a temperature bias drawn per scan from the uncertainty
budget at the part's temperature (emissivity and calibration, about 20 K at 1000 degC). Not the station
end to end: no patterns, decoding, calibration or merge.

Scans (``--scans``, one seed each): the nominal shaft at a uniform 1000 degC with a 0.3 mm dent of 4 mm
sigma on the side away from head 0 (azimuth 225 degrees, 40 mm toward +x), each inspected twice: with
the exact temperatures and with the drawn bias. Parts (``--parts``, one seed each): the first half in
tolerance, the second out by one of diameter, length, ovality or a deep dent in turn, at 950..1100 degC
with an axial gradient and a drawn bias.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from services.formats.part import load_part
from services.inspection.inspect import inspect_field, prepare_part
from services.inspection.uncertainty import TemperatureBudget, temperature_uncertainty
from services.simulation.hot_part import Bump, ScanNoise, all_round_field, hot_shaft, write_shaft_part
from services.simulation.thermal import SurfaceTemperature

SEGMENTS = 360
DENSITY = 4.0
DIAMETER, LENGTH = 90.0, 300.0


def far_side(x: float, radius: float = DIAMETER / 2) -> tuple[float, float, float]:
    """A point of the surface on the azimuth of head 2, away from head 0."""
    angle = np.radians(225.0)
    return (x, radius * np.cos(angle), radius * np.sin(angle))


def seeds(text: str) -> list[int]:
    first, _, last = text.partition("-")
    return list(range(int(first), int(last or first) + 1))


def feature(report, name):
    return next(item for item in report["features"] if item["name"] == name)


def drawn_bias(rng, temperature_c: float) -> float:
    return float(rng.normal(0.0, temperature_uncertainty(temperature_c, TemperatureBudget())["total"]))


def accuracy(prepared, scan_seeds: list[int]) -> None:
    print("| seed | points | bias K | diameter error mm (exact T / biased) | U mm | ovality mm | "
          "length error mm (exact T / biased) | U mm | dent depth mm (exact T / biased) | dent head | "
          "other defects | verdict | inspect s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    errors = {"diameter": [], "diameter_biased": [], "length": [], "length_biased": [], "dent": [],
              "dent_biased": [], "ovality": [], "covered": 0}
    for seed in scan_seeds:
        rng = np.random.default_rng(seed)
        dent = Bump(far_side(40.0), 4.0, -0.3)
        hot = hot_shaft(DIAMETER, LENGTH, segments=SEGMENTS, bumps=(dent,))
        bias = drawn_bias(rng, 1000.0)
        field, truth = all_round_field(hot, rng, points_per_mm2=DENSITY)
        near = np.linalg.norm(truth - np.asarray(dent.center), axis=1) < 4.0
        heads = "/".join(str(head) for head in np.unique(field["head"][near]))
        biased = dict(field, temperature=(field["temperature"] + bias).astype(np.float32))
        started = time.perf_counter()
        exact = inspect_field(field=field, part=prepared).report
        elapsed = time.perf_counter() - started
        report = inspect_field(field=biased, part=prepared).report
        row = {}
        for key, source in (("", exact), ("_biased", report)):
            errors["diameter" + key].append(feature(source, "body_diameter")["cold"] - DIAMETER)
            errors["length" + key].append(feature(source, "length")["cold"] - LENGTH)
            dents = [d["depth"] for d in source["surface"]["defects"] if d["depth"] < 0]
            errors["dent" + key].append(dents[0] + 0.3 if dents else np.nan)
            row[key] = (len(source["surface"]["defects"]) - (1 if dents else 0))
        errors["ovality"].append(feature(report, "body_ovality")["cold"])
        diameter, length = feature(report, "body_diameter"), feature(report, "length")
        covered = (abs(diameter["deviation"]) <= diameter["uncertainty"]
                   and abs(length["deviation"]) <= length["uncertainty"])
        errors["covered"] += covered
        depth = [f"{-0.3 + errors[key][-1]:.3f}" if np.isfinite(errors[key][-1]) else "not found"
                 for key in ("dent", "dent_biased")]
        print(f"| {seed} | {len(field['x'])} | {bias:+.1f} | {errors['diameter'][-1]:+.3f} / "
              f"{errors['diameter_biased'][-1]:+.3f} | {diameter['uncertainty']:.3f} | "
              f"{errors['ovality'][-1]:.3f} | {errors['length'][-1]:+.3f} / {errors['length_biased'][-1]:+.3f} | "
              f"{length['uncertainty']:.3f} | {depth[0]} / {depth[1]} | {heads} | {row['']} / {row['_biased']} | "
              f"{report['verdict']} | {elapsed:.1f} |")
    print("\n| measure | temperatures | median error mm | 95th percentile of abs mm | worst abs mm | target |")
    print("|---|---|---|---|---|---|")
    for name, label, target in (("diameter", "cold diameter", "+-0.05"), ("length", "length", "+-0.1"),
                                ("dent", "dent depth", "+-0.05")):
        for key, temperatures in (("", "exact"), ("_biased", "biased")):
            values = np.asarray(errors[name + key])
            print(f"| {label} | {temperatures} | {np.median(values):+.3f} | "
                  f"{np.percentile(np.abs(values), 95):.3f} | {np.max(np.abs(values)):.3f} | {target} |")
    ovality = np.asarray(errors["ovality"])
    print(f"| ovality of the round shaft (truth 0) | biased | {np.median(ovality):+.3f} | "
          f"{np.percentile(ovality, 95):.3f} | {ovality.max():.3f} | |")
    print(f"\nU covers the diameter's and the length's error (biased) in {errors['covered']} of {len(scan_seeds)} "
          "scans.")


KINDS = ("diameter", "length", "ovality", "dent")


def draw_part(rng, out: bool, kind: str):
    """True cold diameter, length, ovality and bumps of a part in tolerance (``out`` False) or out by ``kind``."""
    diameter = DIAMETER + rng.uniform(-0.1, 0.1)
    length = LENGTH + rng.uniform(-0.2, 0.2)
    ovality = rng.uniform(0.0, 0.12)
    bumps = ((Bump(far_side(rng.uniform(-100, 100)), 4.0, -rng.uniform(0.2, 0.5)),) if rng.random() < 0.5 else ())
    if out:
        sign = rng.choice([-1.0, 1.0])
        if kind == "diameter":
            diameter = DIAMETER + sign * rng.uniform(0.5, 0.8)
        elif kind == "length":
            length = LENGTH + sign * rng.uniform(1.6, 2.0)
        elif kind == "ovality":
            ovality = rng.uniform(0.45, 0.7)
        else:
            bumps = (Bump(far_side(rng.uniform(-100, 100)), 5.0, -rng.uniform(1.6, 2.0)),)
    return diameter, length, ovality, bumps


def verdicts(prepared, part_seeds: list[int]) -> None:
    print("| seed | truth: diameter, length, ovality, dent mm | T degC | bias K | cold diameter | length | ovality | "
          "surface cells mm | expected | verdict | right |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    right = 0
    half = len(part_seeds) // 2
    for index, seed in enumerate(part_seeds):
        rng = np.random.default_rng(seed)
        out = index >= half
        kind = KINDS[(index - half) % len(KINDS)] if out else ""
        diameter, length, ovality, bumps = draw_part(rng, out, kind)
        base = float(rng.uniform(950.0, 1100.0))
        temperature = SurfaceTemperature(base=base, gradient=[float(rng.uniform(-0.2, 0.2)), 0.0, 0.0])
        bias = drawn_bias(rng, base)
        hot = hot_shaft(diameter, length, ovality, temperature, bumps, segments=SEGMENTS)
        field, _ = all_round_field(hot, rng, ScanNoise(temperature_bias_k=bias), points_per_mm2=DENSITY)
        report = inspect_field(field=field, part=prepared).report
        wanted = "NotOK" if out else "OK"
        right += report["verdict"] == wanted
        values = [feature(report, name) for name in ("body_diameter", "length", "body_ovality")]
        cells = ", ".join(f"{item['cold']:.3f} {item['verdict']}" for item in values)
        dent = f"{-bumps[0].height_mm:.2f}" if bumps else "none"
        print(f"| {seed} | {diameter:.3f}, {length:.3f}, {ovality:.3f}, {dent}"
              f"{' (out: ' + kind + ')' if out else ''} | {base:.0f} | {bias:+.1f} | {cells.replace(', ', ' | ')} | "
              f"{report['surface']['cell_min']:+.2f}..{report['surface']['cell_max']:+.2f} {report['surface']['verdict']} | "
              f"{wanted} | {report['verdict']} | "
              f"{'yes' if report['verdict'] == wanted else '**no**'} |")
    print(f"\n{right} of {len(part_seeds)} verdicts right.")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scans", type=seeds, default=seeds("100-109"), help="seeds of the accuracy scans")
    parser.add_argument("--parts", type=seeds, default=seeds("200-219"), help="seeds of the parts judged")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        prepared = prepare_part(load_part(write_shaft_part(Path(directory), DIAMETER, LENGTH, segments=SEGMENTS)))
    print(f"## Accuracy, seeds {args.scans[0]}..{args.scans[-1]}\n")
    accuracy(prepared, args.scans)
    print(f"\n## Verdicts, seeds {args.parts[0]}..{args.parts[-1]}\n")
    verdicts(prepared, args.parts)


if __name__ == "__main__":
    main()
