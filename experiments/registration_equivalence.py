"""Whether two versions of `register` give the same matrices on the real TNO pairs, and how long they take.

For a refactoring of services/registration/register.py: run ``--save`` with the code before it and
``--compare`` with the code after it. Each pair of the chosen half is registered whole and with its infrared
image moved as experiments/registration_real.py moves it (seed 0, what the move brings in set to 0, no mask),
with default options, ``metric="nmi"`` and ``metric="mi"``; ``--compare`` prints, per metric, the largest
corner distance (:func:`services.registration.models.corner_error`, visible pixels) between the saved and the
new matrix and whether every one is under ``--tolerance`` (1e-9 px), and the consistency of each.

``--time`` instead times `register` in-process (default options) on each moved pair, ``--repeats`` times, and
writes the per-pair times as JSON (``--rows-out``); ``--ratio BEFORE.json AFTER.json`` prints the median over
pairs of the ratios of the per-pair medians. Run the two versions alternately in the same minutes, e.g.::

    for r in 1 2 3; do
      PYTHONPATH=/work/main .venv/bin/python experiments/registration_equivalence.py --time --rows-out before_$r.json
      PYTHONPATH=. .venv/bin/python experiments/registration_equivalence.py --time --rows-out after_$r.json
    done
    .venv/bin/python experiments/registration_equivalence.py --ratio before_*.json -- after_*.json

``--evaluations`` instead counts the objective evaluations of default registrations (one thread) of each pair
of the chosen half, whole and moved: at the coarsest pyramid level and at all levels.

``--synthetic N`` instead registers N rendered scenes and N photographs with known matrices
(experiments/registration_accuracy.py's pairs, seed 0) with default options and saves (``--save``) or compares
(``--compare``) each pair's corner error against the truth: whether a change of method makes any pair worse.

The code registered is whichever ``services`` package PYTHONPATH puts first (this clone's otherwise).

Usage: .venv/bin/python experiments/registration_equivalence.py --save base.json [--pairs tuning]
       .venv/bin/python experiments/registration_equivalence.py --compare base.json [--pairs tuning]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parents[1]))  # after PYTHONPATH: the version under test comes first

from experiments.registration_real import SPLITS, load_pair  # noqa: E402
from services.registration.consistency import move_consistency  # noqa: E402
from services.registration.models import corner_error  # noqa: E402
from services.registration.register import register  # noqa: E402
from services.registration.synthetic_pairs import moved_image  # noqa: E402

VARIANTS = {"default": {}, "nmi": {"metric": "nmi"}, "mi": {"metric": "mi"}}


def matrices(numbers: list[int], variants: list[str]) -> list[dict]:
    """Per pair and variant: the whole image's and the moved image's matrices and the consistency."""
    rows = []
    for number in numbers:
        visible, infrared = load_pair(number)
        row = {"pair": number, "size": list(infrared.shape[::-1])}
        for name in variants:
            result = move_consistency(lambda fixed, moving, mask: register(fixed, moving, **VARIANTS[name]).matrix,
                                      visible, infrared, np.random.default_rng([0, number]))
            row[name] = {"unmoved": result.unmoved.tolist(), "moved": result.moved.tolist(),
                         "consistency": result.consistency}
        rows.append(row)
        print(f"pair {number:02d}: " + ", ".join(f"{name} {row[name]['consistency']:.3f} px" for name in variants),
              file=sys.stderr, flush=True)
    return rows


def compare(saved: list[dict], new: list[dict], tolerance: float) -> bool:
    """Print the largest corner distance between saved and new matrices per variant; True if all within."""
    print("| variant | pairs | registrations | largest corner distance (px) | bitwise equal | "
          "consistency median before / after (px) | under 1 px before / after |")
    print("|---|---|---|---|---|---|---|")
    same = True
    for name in VARIANTS:
        pairs = [(old, row) for old, row in zip(saved, new) if name in old and name in row]
        if not pairs:
            continue
        distances, equal = [], 0
        for old, row in pairs:
            width, height = row["size"]
            for key in ("unmoved", "moved"):
                before, after = np.asarray(old[name][key]), np.asarray(row[name][key])
                distances.append(corner_error(before, after, width, height))
                equal += int(np.array_equal(before, after))
        before = np.array([old[name]["consistency"] for old, _ in pairs])
        after = np.array([row[name]["consistency"] for _, row in pairs])
        same &= max(distances) <= tolerance
        print(f"| {name} | {len(pairs)} | {len(distances)} | {max(distances):.3g} | {equal} of {len(distances)} | "
              f"{np.median(before):.3f} / {np.median(after):.3f} | {np.sum(before < 1.0)} / {np.sum(after < 1.0)} |")
    return same


def synthetic_errors(count: int) -> list[dict]:
    """Per rendered scene and photograph (registration_accuracy's pairs, seed 0): the default's corner error."""
    from experiments.registration_accuracy import INFRARED_SIZE, photograph_pairs, scene_pairs

    rng = np.random.default_rng(0)
    rows = []
    for index, (source, visible, infrared, truth, scale) in enumerate(
            list(scene_pairs(rng, count)) + list(photograph_pairs(rng, count))):
        result = register(visible, infrared, "similarity", scale=scale)
        rows.append({"pair": index, "source": source, "error": corner_error(truth, result.matrix, *INFRARED_SIZE)})
    return rows


def compare_errors(saved: list[dict], new: list[dict]) -> None:
    """Print the per-source summary of saved and new corner errors and the pairs that got worse."""
    print("| source | n | median before / after (px) | under 1 px before / after | max before / after (px) | "
          "pairs worse by > 0.01 px | largest change (px) |")
    print("|---|---|---|---|---|---|---|")
    for source in ("scene", "photograph"):
        before = np.array([row["error"] for row in saved if row["source"] == source])
        after = np.array([row["error"] for row in new if row["source"] == source])
        change = after - before
        print(f"| {source} | {len(before)} | {np.median(before):.3f} / {np.median(after):.3f} | "
              f"{np.sum(before < 1.0)} / {np.sum(after < 1.0)} | {before.max():.2f} / {after.max():.2f} | "
              f"{np.sum(change > 0.01)} | {change[np.argmax(np.abs(change))]:+.3f} |")


def timings(numbers: list[int], repeats: int) -> dict:
    """Per pair, the wall-clock seconds of each of ``repeats`` default registrations of the moved image."""
    times = {}
    for number in numbers:
        visible, infrared = load_pair(number)
        moved, _, _ = moved_image(np.random.default_rng([0, number]), infrared)
        register(visible, moved)  # warm the thread pool and the caches
        seconds = []
        for _ in range(repeats):
            start = time.perf_counter()
            register(visible, moved)
            seconds.append(time.perf_counter() - start)
        times[str(number)] = seconds
        print(f"pair {number:02d}: {np.median(seconds):.2f} s", file=sys.stderr, flush=True)
    return times


def evaluations(numbers: list[int]) -> dict:
    """Objective evaluations of default registrations (one thread) of each pair, whole and moved: at the coarsest
    level and at all levels, counted by wrapping each level's objective (``register._build_pyramid``)."""
    from services.registration import register as module

    counts = {"coarsest": 0, "all": 0}
    build = module._build_pyramid

    def counted_pyramid(*args, **kwargs):
        pyramid = build(*args, **kwargs)

        def counted(level, factory):
            def objective():
                function = factory()

                def evaluate(samples):
                    counts["all"] += 1
                    counts["coarsest"] += level == pyramid.coarsest
                    return function(samples)
                return evaluate
            return objective

        return dataclasses.replace(pyramid, objectives=[counted(level, factory)
                                                        for level, factory in enumerate(pyramid.objectives)])

    module._build_pyramid = counted_pyramid
    try:
        for number in numbers:
            visible, infrared = load_pair(number)
            moved, _, _ = moved_image(np.random.default_rng([0, number]), infrared)
            for image in (infrared, moved):
                module.register(visible, image, threads=1)
    finally:
        module._build_pyramid = build
    return counts


def ratio(before: list[Path], after: list[Path]) -> None:
    """The median over pairs of after / before, each the median of all its runs."""
    def pooled(paths: list[Path]) -> dict:
        runs: dict = {}
        for path in paths:
            for number, seconds in json.loads(path.read_text()).items():
                runs.setdefault(number, []).extend(seconds)
        return {number: float(np.median(seconds)) for number, seconds in runs.items()}

    old, new = pooled(before), pooled(after)
    print("| pair | before, median (s) | after, median (s) | after / before |")
    print("|---|---|---|---|")
    ratios = []
    for number in sorted(old, key=int):
        ratios.append(new[number] / old[number])
        print(f"| {int(number):02d} | {old[number]:.3f} | {new[number]:.3f} | {ratios[-1]:.3f} |")
    print(f"\nmedian of the per-pair ratios {np.median(ratios):.3f}; summed times {sum(new.values()):.2f} s after "
          f"against {sum(old.values()):.2f} s before (ratio {sum(new.values()) / sum(old.values()):.3f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", nargs="+", default=["tuning"],
                        help="'tuning' (odd, the default), 'reporting' (even), 'all' or pair numbers")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--save", type=Path, help="register and save the matrices")
    parser.add_argument("--compare", type=Path, help="register and compare with saved matrices")
    parser.add_argument("--tolerance", type=float, default=1e-9, help="largest corner distance allowed (px)")
    parser.add_argument("--synthetic", type=int, metavar="N",
                        help="corner errors of N rendered scenes and N photographs with default options instead")
    parser.add_argument("--time", action="store_true", help="time default registrations of the moved pairs")
    parser.add_argument("--evaluations", action="store_true",
                        help="count the objective evaluations of default registrations, whole and moved")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--rows-out", type=Path)
    parser.add_argument("--ratio", type=Path, nargs="+", metavar="JSON",
                        help="BEFORE.json ... -- AFTER.json ...: the time ratio of two --time runs' files")
    args, rest = parser.parse_known_args()
    numbers = [number for item in args.pairs for number in (SPLITS[item] if item in SPLITS else [int(item)])]
    if args.ratio:
        after = [Path(item) for item in rest if item != "--"]
        ratio(args.ratio, after)
        return
    if args.evaluations:
        counts = evaluations(numbers)
        print(f"{len(numbers)} pairs, whole and moved, default options, one thread: {counts['coarsest']} objective "
              f"evaluations at the coarsest level, {counts['all']} at all levels")
        return
    if args.time:
        times = timings(numbers, args.repeats)
        if args.rows_out is not None:
            args.rows_out.write_text(json.dumps(times))
        return
    if args.synthetic:
        rows = synthetic_errors(args.synthetic)
        if args.save is not None:
            args.save.write_text(json.dumps(rows))
        if args.compare is not None:
            compare_errors(json.loads(args.compare.read_text()), rows)
        return
    rows = matrices(numbers, args.variants)
    if args.save is not None:
        args.save.write_text(json.dumps(rows))
    if args.compare is not None:
        if not compare(json.loads(args.compare.read_text()), rows, args.tolerance):
            sys.exit(1)


if __name__ == "__main__":
    main()
