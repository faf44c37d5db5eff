"""Where `register`'s time goes: CPU time of each step on the moved TNO pairs, with the evaluations per level.

Each pair's infrared image is moved as ``benchmarks/bench_registration.py --tno`` moves it (seed 0, what the
move brings in set to 0) and registered in-process with default options (no mask), in one thread so that
the CPU times add up; each step of :func:`services.registration.register.register` is timed on its own
(``time.process_time``: the load of a shared machine stretches the wall clock, not this), the median of
``--repeats`` runs. The steps: the border mask, the pyramids, the exhaustive search at the coarsest level,
the choice (the refinements of the proposals at the coarsest level until five distinct maxima, then of each
distinct maximum one level finer) and the descent to full resolution; "evaluations" counts the objective's
evaluations per level, coarsest first.

Usage: .venv/bin/python benchmarks/bench_registration_stages.py [--pairs 24 06 20] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import services.registration.register as registration  # noqa: E402
from experiments.registration_real import REPORTING, load_pair  # noqa: E402
from services.registration.objective import FixedSampler  # noqa: E402
from services.registration.synthetic_pairs import moved_image  # noqa: E402

STEPS = ("mask", "pyramid", "search", "choice", "descent", "result")


def _stages(visible: np.ndarray, moving: np.ndarray) -> tuple[dict[str, float], dict[tuple[int, int], int]]:
    """CPU seconds of each step of one registration with default options, and the evaluations per level size."""
    evaluations: dict[tuple[int, int], int] = {}
    sampler_call = FixedSampler.__call__

    def counted(sampler: FixedSampler, matrix: np.ndarray) -> np.ndarray:
        size = sampler.size[::-1]
        evaluations[size] = evaluations.get(size, 0) + 1
        return sampler_call(sampler, matrix)

    seconds: dict[str, float] = {}

    def timed(step: str, function, *args):
        start = time.process_time()
        result = function(*args)
        seconds[step] = time.process_time() - start
        return result

    FixedSampler.__call__ = counted
    try:
        plan = registration._PLANS[registration.DEFAULT_METRIC](
            registration.DEFAULT_BINS, registration.DEFAULT_LOG_BASE, 0.3)
        mask = timed("mask", registration.data_mask, moving)
        nominal = registration._nominal_scale(visible, moving, None)
        reduction = min(1.0, 1.0 / nominal)
        pyramid = timed("pyramid", registration._build_pyramid, plan, visible, moving, mask, reduction, None)
        candidates = timed("search", registration._global_search, plan, pyramid, "similarity", nominal, reduction,
                           None, 6.0, 0.12)
        evaluations.clear()  # the search's canvases are not evaluations of the objective
        refine = registration._Refiner(pyramid, "similarity", plan.cubic, 1)
        matrix, level = timed("choice", plan.choose, candidates, refine)
        matrix = timed("descent", registration._descend, plan, refine, matrix, level)
        counts = dict(evaluations)  # the result's sampling is not one either
        timed("result", registration._registration, pyramid, matrix, "similarity", reduction,
              registration.DEFAULT_BINS, registration.DEFAULT_LOG_BASE)
    finally:
        FixedSampler.__call__ = sampler_call
    return seconds, counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=list(REPORTING))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cv2.setNumThreads(1)  # as the command
    print(f"CPU seconds, median of {args.repeats} runs, one thread\n")
    print("| pair | " + " | ".join(STEPS) + " | total | evaluations per level, coarsest first |")
    print("|---" * (len(STEPS) + 3) + "|")
    for number in args.pairs:
        visible, infrared = load_pair(number)
        moving, _, _ = moved_image(np.random.default_rng([0, number]), infrared)
        runs = [_stages(visible, moving) for _ in range(args.repeats)]
        medians = {step: float(np.median([seconds[step] for seconds, _ in runs])) for step in STEPS}
        counts = runs[0][1]
        levels = ", ".join(f"{counts[size]} at {size[1]}x{size[0]}"
                           for size in sorted(counts, key=lambda shape: shape[0] * shape[1]))
        print(f"| {number:02d} | " + " | ".join(f"{medians[step]:.3f}" for step in STEPS)
              + f" | {sum(medians.values()):.3f} | {levels} |")
    load = os.getloadavg()
    print(f"\nload average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} on {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
