"""Benchmark: thermofield MI registration against SimpleITK's Mattes MI registration, same pairs, same run.

Both register a 320x256 infrared image to its visible image with a similarity
model, starting from the same nominal alignment (centres matched, nominal
scale). SimpleITK: Mattes mutual information (32 bins, all pixels), linear
interpolation, regular-step gradient descent with physical-shift scales,
three levels (shrink 4, 2, 1; smoothing 2, 1, 0 px), the infrared image as
its fixed image so that its transform maps infrared to visible points as our
matrix does; once on the grey images and once on gradient magnitudes.

Pairs as experiments/registration_accuracy.py: rendered scenes (1024x768
visible) and real photographs (640x480) with a synthetic infrared modality,
moved by shifts up to 40 px, rotations up to 5 degrees, scale changes up to
10 %. Each registration is timed ``--repeats`` times; the per-pair median
wall-clock and CPU times are summarised by their median over pairs, and the
ratio is SimpleITK's median over ours.

With ``--command``, instead: the whole ``thermofield register --model similarity`` process on
benchmarks/bench_commands.py's 500x300 TNO pair against SimpleITK's registration of the same pair in-process,
alternating, ``--repeats`` times each; wall-clock medians and the processes' CPU times (the command's from
``getrusage`` of its child process), with the load average.

With ``--tno``, instead: on each real TNO pair of the reporting half (the even numbers; the defaults were
chosen on the odd ones), the infrared image moved as experiments/registration_real.py moves it (seed 0, what
the move brings in set to 0), the whole ``thermofield register`` process with default options (no mask)
against SimpleITK's registration of the same moved pair in-process (given the mask of the pixels with data,
its best case), alternating, ``--repeats`` times each; per pair the median wall-clock times and their ratio,
then the median of the ratios and the ratio of the summed medians. With ``--baseline CHECKOUT`` as well, the
reference is the same command run from another checkout of the project (its own code on PYTHONPATH, this
environment's Python) instead of SimpleITK: a change's speed-up measured on the same pairs in the same run, with
the processes' CPU times (``getrusage`` of the children), which the load disturbs less than the wall-clock times.

Usage: .venv/bin/python benchmarks/bench_registration.py [--pairs-per-source 10] [--repeats 3] [--command | --tno
       [--baseline CHECKOUT]]
Needs the bench extra (SimpleITK), except ``--tno --baseline``.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.registration_accuracy import INFRARED_SIZE, photograph_pairs, scene_pairs  # noqa: E402
from services.registration.models import corner_error  # noqa: E402
from services.registration.preprocess import gradient_magnitude  # noqa: E402
from services.registration.register import register  # noqa: E402


def _nominal_scale(visible: np.ndarray, infrared: np.ndarray, scale: float | None) -> float:
    if scale is not None:
        return scale
    return min(visible.shape[1] / infrared.shape[1], visible.shape[0] / infrared.shape[0])


def simpleitk_register(visible: np.ndarray, infrared: np.ndarray, scale: float | None, gradient: bool,
                       infrared_mask: np.ndarray | None = None) -> np.ndarray:
    """SimpleITK Mattes-MI similarity registration; returns the infrared-to-visible matrix.

    ``infrared_mask`` marks the infrared pixels that have data (ITK's fixed-image mask: the infrared image is
    the one ITK samples)."""
    import SimpleITK as sitk  # the bench extra; --tno --baseline runs without it

    nominal = _nominal_scale(visible, infrared, scale)
    if gradient:
        visible_image, infrared_image = gradient_magnitude(visible, 0.5 * nominal), gradient_magnitude(infrared, 0.5)
    else:
        visible_image, infrared_image = visible.astype(np.float32), infrared.astype(np.float32)
    fixed = sitk.GetImageFromArray(infrared_image.astype(np.float32))
    moving = sitk.GetImageFromArray(visible_image.astype(np.float32))
    height, width = infrared.shape
    centre = ((width - 1) / 2.0, (height - 1) / 2.0)
    shift = ((visible.shape[1] - 1) / 2.0 - centre[0], (visible.shape[0] - 1) / 2.0 - centre[1])
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsMattesMutualInformation(numberOfHistogramBins=32)
    method.SetMetricSamplingStrategy(method.NONE)
    if infrared_mask is not None:
        method.SetMetricFixedMask(sitk.GetImageFromArray(np.asarray(infrared_mask, dtype=np.uint8)))
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(learningRate=2.0, minStep=1e-3, numberOfIterations=300,
                                                   relaxationFactor=0.5)
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel([4, 2, 1])
    method.SetSmoothingSigmasPerLevel([2, 1, 0])
    method.SetInitialTransform(sitk.Similarity2DTransform(nominal, 0.0, shift, centre), inPlace=False)
    transform = sitk.Similarity2DTransform(method.Execute(fixed, moving).GetNthTransform(0))
    linear = np.asarray(transform.GetMatrix()).reshape(2, 2)
    centre = np.asarray(transform.GetCenter())
    matrix = np.eye(3)
    matrix[:2, :2] = linear
    matrix[:2, 2] = centre + np.asarray(transform.GetTranslation()) - linear @ centre
    return matrix


METHODS = {
    "thermofield (gradient, NMI)": lambda visible, infrared, scale: register(
        visible, infrared, "similarity", preprocessing="gradient", metric="nmi", scale=scale).matrix,
    "SimpleITK Mattes (grey)": lambda visible, infrared, scale: simpleitk_register(visible, infrared, scale, False),
    "SimpleITK Mattes (gradient)": lambda visible, infrared, scale: simpleitk_register(visible, infrared, scale, True),
}


def command_against_simpleitk(repeats: int) -> None:
    """Whole `thermofield register` processes against SimpleITK in-process on one 500x300 pair (see the docstring)."""
    from benchmarks.bench_commands import ROOT, _make_pair, _thermofield, child_environment

    times: dict[str, dict[str, list[float]]] = {name: {"wall": [], "cpu": []} for name in ("command", "SimpleITK")}
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        visible_path, infrared_path, visible, infrared = _make_pair(work)
        command = _thermofield("register", "--fixed", visible_path, "--moving", infrared_path, "--model", "similarity",
                               "--out", work / "reg.json")
        env = child_environment(PYTHONPATH=str(ROOT))
        for _ in range(repeats):
            before = resource.getrusage(resource.RUSAGE_CHILDREN)
            wall = time.perf_counter()
            subprocess.run(command, cwd=ROOT, env=env, check=True, capture_output=True)
            times["command"]["wall"].append(time.perf_counter() - wall)
            after = resource.getrusage(resource.RUSAGE_CHILDREN)
            times["command"]["cpu"].append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
            wall, cpu = time.perf_counter(), time.process_time()
            simpleitk_register(visible, infrared, 1.0, gradient=False)
            times["SimpleITK"]["wall"].append(time.perf_counter() - wall)
            times["SimpleITK"]["cpu"].append(time.process_time() - cpu)
    load = os.getloadavg()
    print(f"{repeats} runs each, alternating; load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
          f"on {os.cpu_count()} cores\n")
    print("| what | median wall (s) | median CPU (s) | wall ratio to SimpleITK | CPU ratio to SimpleITK |")
    print("|---|---|---|---|---|")
    reference = {kind: float(np.median(times["SimpleITK"][kind])) for kind in ("wall", "cpu")}
    for name, label in (("command", "`thermofield register --model similarity` (whole process)"),
                        ("SimpleITK", "SimpleITK Mattes MI, in-process")):
        wall, cpu = float(np.median(times[name]["wall"])), float(np.median(times[name]["cpu"]))
        print(f"| {label} | {wall:.3f} | {cpu:.3f} | {wall / reference['wall']:.2f} | {cpu / reference['cpu']:.2f} |")


def _written_moved_pairs(work: Path):
    """The reporting half's TNO pairs, each infrared image moved on its own canvas (the seeded similarity of
    ``moved_image``), written to ``work/vi.png`` and ``work/ir.png``: (number, visible, infrared, moved, mask)."""
    import cv2

    from experiments.registration_real import REPORTING, load_pair
    from services.registration.synthetic_pairs import moved_image

    for number in REPORTING:
        visible, infrared = load_pair(number)
        moved, mask, _ = moved_image(np.random.default_rng([0, number]), infrared)
        for name, image in (("vi.png", visible), ("ir.png", moved)):
            cv2.imwrite(str(work / name), image)
        yield number, visible, infrared, moved, mask


def tno_commands_against_simpleitk(repeats: int) -> None:
    """Whole `thermofield register` processes against SimpleITK in-process on the moved TNO pairs of the
    reporting half."""
    from benchmarks.bench_commands import ROOT, _thermofield, child_environment

    env = child_environment(PYTHONPATH=str(ROOT))
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        for number, visible, infrared, moved, mask in _written_moved_pairs(work):
            command = _thermofield("register", "--fixed", work / "vi.png", "--moving", work / "ir.png",
                                   "--out", work / "reg.json")
            commands, references = [], []
            for _ in range(repeats):
                wall = time.perf_counter()
                subprocess.run(command, cwd=ROOT, env=env, check=True, capture_output=True)
                commands.append(time.perf_counter() - wall)
                wall = time.perf_counter()
                simpleitk_register(visible, moved, 1.0, gradient=False, infrared_mask=mask)
                references.append(time.perf_counter() - wall)
            rows.append((number, infrared.shape[::-1], float(np.median(commands)), float(np.median(references))))
    load = os.getloadavg()
    ratios = [command / reference for _, _, command, reference in rows]
    print(f"{repeats} runs each per pair, alternating; load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
          f"on {os.cpu_count()} cores\n")
    print("| pair | size | `thermofield register` whole process, median (s) | SimpleITK in-process, median (s) | ratio |")
    print("|---|---|---|---|---|")
    for (number, (width, height), command, reference), ratio in zip(rows, ratios):
        print(f"| {number:02d} | {width}x{height} | {command:.3f} | {reference:.3f} | {ratio:.2f} |")
    summed = sum(row[2] for row in rows) / sum(row[3] for row in rows)
    print(f"\nmedian of the per-pair ratios {np.median(ratios):.2f}; no slower on {sum(r <= 1.0 for r in ratios)} of "
          f"{len(ratios)} pairs; ratio of the summed times {summed:.2f}")


def tno_commands_against_baseline(repeats: int, baseline: Path) -> None:
    """Whole `thermofield register` processes of this checkout against those of ``baseline`` on the moved TNO
    pairs of the reporting half, alternating; wall-clock and CPU medians per pair and their ratios."""
    from benchmarks.bench_commands import ROOT, child_environment

    if not (baseline / "services" / "cli" / "main.py").is_file():
        raise SystemExit(f"--baseline {baseline}: not a checkout of the project (no services/cli/main.py)")
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        for number, visible, infrared, moved, _ in _written_moved_pairs(work):
            times: dict[Path, dict[str, list[float]]] = {root: {"wall": [], "cpu": []} for root in (ROOT, baseline)}
            for _ in range(repeats):
                for root in (ROOT, baseline):
                    command = [sys.executable, "-m", "services.cli.main", "register", "--fixed", str(work / "vi.png"),
                               "--moving", str(work / "ir.png"), "--out", str(work / "reg.json")]
                    before = resource.getrusage(resource.RUSAGE_CHILDREN)
                    wall = time.perf_counter()
                    subprocess.run(command, cwd=root, env=child_environment(PYTHONPATH=str(root)), check=True,
                                   capture_output=True)
                    times[root]["wall"].append(time.perf_counter() - wall)
                    after = resource.getrusage(resource.RUSAGE_CHILDREN)
                    times[root]["cpu"].append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
            rows.append((number, infrared.shape[::-1], *(float(np.median(times[root][kind]))
                                                         for root in (ROOT, baseline) for kind in ("wall", "cpu"))))
    load = os.getloadavg()
    print(f"{repeats} runs each per pair, alternating; load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} "
          f"on {os.cpu_count()} cores; baseline {baseline}\n")
    print("| pair | size | this checkout: wall, median (s) | CPU (s) | baseline: wall, median (s) | CPU (s) | "
          "wall ratio | CPU ratio |")
    print("|---|---|---|---|---|---|---|---|")
    for number, (width, height), wall, cpu, base_wall, base_cpu in rows:
        print(f"| {number:02d} | {width}x{height} | {wall:.3f} | {cpu:.3f} | {base_wall:.3f} | {base_cpu:.3f} | "
              f"{wall / base_wall:.2f} | {cpu / base_cpu:.2f} |")
    table = np.asarray([row[2:] for row in rows])
    print(f"\nmedian of the per-pair ratios: wall {np.median(table[:, 0] / table[:, 2]):.3f}, CPU "
          f"{np.median(table[:, 1] / table[:, 3]):.3f}; ratio of the summed medians: wall "
          f"{table[:, 0].sum() / table[:, 2].sum():.3f}, CPU {table[:, 1].sum() / table[:, 3].sum():.3f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs-per-source", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--command", action="store_true",
                        help="time the whole register command against SimpleITK in-process instead")
    parser.add_argument("--tno", action="store_true",
                        help="time the whole register command against SimpleITK on the moved TNO pairs of the "
                             "reporting half instead")
    parser.add_argument("--baseline", type=Path, metavar="CHECKOUT",
                        help="with --tno: time the register command of this other checkout of the project instead of "
                             "SimpleITK (e.g. the code before a change; `git worktree add` or `git archive` makes one)")
    args = parser.parse_args()
    if args.command:
        command_against_simpleitk(args.repeats)
        return
    if args.tno and args.baseline is not None:
        tno_commands_against_baseline(args.repeats, args.baseline.resolve())
        return
    if args.tno:
        tno_commands_against_simpleitk(args.repeats)
        return
    if args.baseline is not None:
        parser.error("--baseline times the --tno pairs: give --tno too")
    rng = np.random.default_rng(args.seed)
    pairs = list(scene_pairs(rng, args.pairs_per_source)) + list(photograph_pairs(rng, args.pairs_per_source))
    results = {name: {"error": [], "wall": [], "cpu": []} for name in METHODS}
    for _, visible, infrared, truth, scale in pairs:
        for name, method in METHODS.items():
            walls, cpus = [], []
            for _ in range(args.repeats):
                wall, cpu = time.perf_counter(), time.process_time()
                matrix = method(visible, infrared, scale)
                walls.append(time.perf_counter() - wall)
                cpus.append(time.process_time() - cpu)
            results[name]["error"].append(corner_error(truth, matrix, *INFRARED_SIZE))
            results[name]["wall"].append(float(np.median(walls)))
            results[name]["cpu"].append(float(np.median(cpus)))
    ours = results["thermofield (gradient, NMI)"]
    print(f"{len(pairs)} pairs ({args.pairs_per_source} rendered scenes + {args.pairs_per_source} photographs), "
          f"{args.repeats} repeats, {__import__('SimpleITK').Version.VersionString()} SimpleITK\n")
    print("| method | median corner error (px) | under 1 px | max (px) | median wall time (s) | "
          "wall-time ratio to ours | median CPU time (s) | CPU-time ratio to ours |")
    print("|---|---|---|---|---|---|---|---|")
    for name, result in results.items():
        errors = np.asarray(result["error"])
        wall, cpu = np.median(result["wall"]), np.median(result["cpu"])
        print(f"| {name} | {np.median(errors):.3f} | {100 * np.mean(errors < 1.0):.0f} % | {errors.max():.2f} | "
              f"{wall:.2f} | {wall / np.median(ours['wall']):.2f} | {cpu:.2f} | {cpu / np.median(ours['cpu']):.2f} |")


if __name__ == "__main__":
    main()
