"""Registration of the 25 real TNO infrared/visible pairs: consistency under known moves, beside SimpleITK.

The pairs (../shared/data/tno-ir-visible) were aligned by hand to about a
pixel, which is not ground truth at the sub-pixel level. So precision is
measured as consistency: each infrared image is moved by a known similarity
S (each shift component up to 30 px, rotation up to 4 degrees, scale
0.93..1.07, seeded) and cut to a view inside the original
(services.registration.synthetic_pairs.moved_view); the registration H1 of
the moved view must equal the registration H0 of the unmoved image composed
with the move, H0 S^-1. Consistency = mean distance of the view's four corner
pixels under H1 and H0 S^-1 (visible pixels). The distance of H0 to the hand
alignment (the identity) is reported too.

Methods, same pairs, same run: thermofield (`register`, similarity, default
preprocessing and metric, nominal scale 1, shift range 45 px) and
SimpleITK's Mattes MI (benchmarks/bench_registration.py's settings, from
the centred start). Times: each method in-process, and the whole
`thermofield register` process (python -m services.cli.main, start-up
included) on the moved pair.

Usage: .venv/bin/python experiments/registration_real.py [--pairs 1 2 ...] [--seed 0] [--no-simpleitk]
       [--no-cli] [--figure]
Prints Markdown tables; --figure writes docs/figures/registration/real_pair_*.png.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.formats.registration import load_registration  # noqa: E402
from services.registration.models import corner_error  # noqa: E402
from services.registration.overlay import fused_overlay  # noqa: E402
from services.registration.register import register  # noqa: E402
from services.registration.synthetic_pairs import moved_view  # noqa: E402

TNO_DIR = ROOT.parent / "shared" / "data" / "tno-ir-visible"  # shared/ beside the clone
FIGURES = ROOT / "docs" / "figures" / "registration"
MAX_SHIFT = 45.0  # search range: the 30 px moves per axis (up to 42 px) plus the hand alignment's error


def load_pair(number: int) -> tuple[np.ndarray, np.ndarray]:
    """The visible and infrared grey images of TNO pair ``number`` (1..25)."""
    images = []
    for band in ("vi", "ir"):
        path = TNO_DIR / band / f"{number:02d}.png"
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"{path}: the TNO image is missing or unreadable")
        images.append(image)
    return images[0], images[1]


def moved_pairs(numbers: list[int], seed: int):
    """(number, visible, infrared, moved infrared view, view-to-infrared matrix); pair n's move is seeded by (seed, n)."""
    for number in numbers:
        visible, infrared = load_pair(number)
        moved, view_to_infrared = moved_view(np.random.default_rng([seed, number]), infrared)
        yield number, visible, infrared, moved, view_to_infrared


def thermofield_matrix(visible: np.ndarray, infrared: np.ndarray) -> np.ndarray:
    return register(visible, infrared, "similarity", scale=1.0, max_shift=MAX_SHIFT).matrix


def simpleitk_matrix(visible: np.ndarray, infrared: np.ndarray) -> np.ndarray:
    from benchmarks.bench_registration import simpleitk_register

    return simpleitk_register(visible, infrared, 1.0, gradient=False)


def cli_matrix(visible: np.ndarray, infrared: np.ndarray) -> tuple[np.ndarray, float]:
    """The matrix from a whole `thermofield register` process, and that process's wall-clock time."""
    with tempfile.TemporaryDirectory() as folder:
        fixed, moving, out = Path(folder) / "vi.png", Path(folder) / "ir.png", Path(folder) / "reg.json"
        cv2.imwrite(str(fixed), visible)
        cv2.imwrite(str(moving), infrared)
        command = [sys.executable, "-m", "services.cli.main", "register", "--fixed", str(fixed), "--moving",
                   str(moving), "--scale", "1", "--max-shift", str(MAX_SHIFT), "--out", str(out)]
        start = time.perf_counter()
        subprocess.run(command, check=True, cwd=ROOT, capture_output=True,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
        seconds = time.perf_counter() - start
        return np.asarray(load_registration(out).matrix, dtype=float), seconds


def _timed(method, *images) -> tuple[np.ndarray, float]:
    start = time.perf_counter()
    matrix = method(*images)
    return matrix, time.perf_counter() - start


def evaluate(numbers: list[int], seed: int, simpleitk: bool, cli: bool) -> list[dict]:
    rows = []
    methods = {"thermofield": thermofield_matrix}
    if simpleitk:
        methods["SimpleITK Mattes"] = simpleitk_matrix
    for number, visible, infrared, moved, view_to_infrared in moved_pairs(numbers, seed):
        row = {"pair": number, "size": infrared.shape[::-1], "view": moved.shape[::-1]}
        height, width = infrared.shape
        for name, method in methods.items():
            unmoved, _ = _timed(method, visible, infrared)
            matrix, seconds = _timed(method, visible, moved)
            row[name] = {
                "consistency": corner_error(unmoved @ view_to_infrared, matrix, moved.shape[1], moved.shape[0]),
                "hand": corner_error(np.eye(3), unmoved, width, height),
                "seconds": seconds,
                "unmoved": unmoved,
            }
        if cli:
            matrix, seconds = cli_matrix(visible, moved)
            row["cli"] = {"seconds": seconds,
                          "agrees": corner_error(row["thermofield"]["unmoved"] @ view_to_infrared, matrix,
                                                 moved.shape[1], moved.shape[0])}
        rows.append(row)
        print(f"pair {number}: " + ", ".join(f"{name} {row[name]['consistency']:.3f} px" for name in methods),
              file=sys.stderr, flush=True)
    return rows


def _summary(values: list[float]) -> str:
    values = np.asarray(values)
    return (f"{np.median(values):.3f} | {np.percentile(values, 90):.3f} | {100.0 * np.mean(values < 1.0):.0f} % | "
            f"{values.max():.2f}")


def print_tables(rows: list[dict]) -> None:
    methods = [name for name in ("thermofield", "SimpleITK Mattes") if name in rows[0]]
    print("| pair | size | view | " + " | ".join(f"{name} consistency (px) | {name} from hand (px)"
                                                 for name in methods) + " |")
    print("|---|---|---|" + "---|---|" * len(methods))
    for row in rows:
        cells = " | ".join(f"{row[name]['consistency']:.3f} | {row[name]['hand']:.2f}" for name in methods)
        print(f"| {row['pair']:02d} | {row['size'][0]}x{row['size'][1]} | {row['view'][0]}x{row['view'][1]} | "
              f"{cells} |")
    print("\n| method | n | consistency median (px) | 90th pct (px) | under 1 px | max (px) | "
          "from hand, median (px) | median time in-process (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for name in methods:
        consistency = [row[name]["consistency"] for row in rows]
        hand = np.median([row[name]["hand"] for row in rows])
        seconds = np.median([row[name]["seconds"] for row in rows])
        print(f"| {name} | {len(rows)} | {_summary(consistency)} | {hand:.2f} | {seconds:.2f} |")
    if "cli" in rows[0]:
        seconds = np.median([row["cli"]["seconds"] for row in rows])
        agrees = np.median([row["cli"]["agrees"] for row in rows])
        print(f"\n`thermofield register` whole process: median {seconds:.2f} s per pair "
              f"(its matrix vs the in-process consistency reference: median {agrees:.3f} px)")


def figure(number: int, seed: int) -> None:
    """Overlay of one real pair at the hand alignment and after registration, side by side."""
    visible, infrared = load_pair(number)
    matrix = thermofield_matrix(visible, infrared)
    FIGURES.mkdir(parents=True, exist_ok=True)
    before, after = fused_overlay(visible, infrared, np.eye(3)), fused_overlay(visible, infrared, matrix)
    cv2.imwrite(str(FIGURES / f"real_pair_{number:02d}.png"), np.hstack([before, after]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, nargs="+", default=list(range(1, 26)))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-simpleitk", action="store_true")
    parser.add_argument("--no-cli", action="store_true")
    parser.add_argument("--figure", type=int, metavar="PAIR", help="write the before/after overlay of this pair")
    args = parser.parse_args()
    rows = evaluate(args.pairs, args.seed, not args.no_simpleitk, not args.no_cli)
    print_tables(rows)
    if args.figure is not None:
        figure(args.figure, args.seed)


if __name__ == "__main__":
    main()
