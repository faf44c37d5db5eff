"""Registration of the 25 real TNO infrared/visible pairs: consistency under known moves, beside SimpleITK.

The pairs (../shared/data/tno-ir-visible) were aligned by hand to about a
pixel, which is not ground truth at the sub-pixel level. So precision is
measured as consistency: each infrared image is moved by a known similarity
S (each shift component up to 30 px, rotation up to 4 degrees, scale
0.93..1.07, seeded by the pair number) on its own canvas, what the move
brings in from outside set to 0 (--protocol moved, the default:
services.registration.synthetic_pairs.moved_image), or cut to a view inside
the original (--protocol view: moved_view); the registration H1 of the moved
image must equal the registration H0 of the unmoved image composed with the
move, H0 S^-1 (services.registration.consistency). Consistency = mean
distance of the moved image's four corner pixels under H1 and H0 S^-1
(visible pixels). The distance of H0 to the hand alignment (the identity)
is reported too.

The pairs are split by number: the odd ones (01, 03, ... 25) are the tuning
half, on which the registration's defaults were chosen (--pairs tuning);
the even ones (02, 04, ... 24) the reporting half (--pairs reporting), whose
figures the docs and tests quote.

Methods, same pairs, same run: thermofield (`register` with every default:
no mask, no metric, no scale or search range given; it finds the border the
move brought in itself), thermofield with ``metric="nmi"`` (else the
defaults), and SimpleITK's Mattes MI (benchmarks/bench_registration.py's
settings, from the centred start, given the mask of the moved image's pixels
with data: its best case). ``--option KEY=VALUE`` passes a keyword to
thermofield's `register` (how the defaults were chosen; ``shift=F`` sets
max_shift to F times the infrared image's smaller side). Times: each method
in-process, and the whole `thermofield register` process (python -m
services.cli.main, start-up included, default options) on the moved pair.

Usage: .venv/bin/python experiments/registration_real.py [--protocol moved|view]
       [--pairs tuning|reporting|all|N ...] [--seed 0] [--methods NAME ...] [--option KEY=VALUE ...] [--no-cli]
       [--figure N] [--moved-figure N] [--rows-out rows.json] [--from-rows a.json b.json ...] [--objective-check]
Prints Markdown tables; --figure N writes docs/figures/registration/real_pair_NN_edges.png, --moved-figure N
real_pair_NN_moved.png.
"""

from __future__ import annotations

import argparse
import json
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
from services.registration.borders import data_mask  # noqa: E402
from services.registration.consistency import move_consistency  # noqa: E402
from services.registration.models import corner_error  # noqa: E402
from services.registration.register import objective_value, register  # noqa: E402
from services.registration.synthetic_pairs import moved_image  # noqa: E402

TNO_DIR = ROOT.parent / "shared" / "data" / "tno-ir-visible"  # shared/ beside the clone
FIGURES = ROOT / "docs" / "figures" / "registration"
TUNING = tuple(range(1, 26, 2))  # the registration's defaults were chosen on these pairs only
REPORTING = tuple(range(2, 26, 2))  # figures are reported on these pairs only
SPLITS = {"tuning": TUNING, "reporting": REPORTING, "all": tuple(range(1, 26))}


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


OPTIONS: dict = {}  # keyword arguments of thermofield's `register` beyond its defaults (--option)


def _options(infrared: np.ndarray, options: dict) -> dict:
    """``options`` with ``shift`` (a fraction of the infrared image's smaller side) turned into ``max_shift``."""
    options = dict(options)
    if "shift" in options:
        options["max_shift"] = float(options.pop("shift")) * min(infrared.shape)
    return options


def thermofield_matrix(visible: np.ndarray, infrared: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """`register` with its defaults (and --option's); ``mask`` is not passed: it finds the border itself."""
    return register(visible, infrared, **_options(infrared, OPTIONS)).matrix


def thermofield_nmi_matrix(visible: np.ndarray, infrared: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    return register(visible, infrared, metric="nmi").matrix


def simpleitk_matrix(visible: np.ndarray, infrared: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    from benchmarks.bench_registration import simpleitk_register

    return simpleitk_register(visible, infrared, 1.0, gradient=False, infrared_mask=mask)


def cli_matrix(visible: np.ndarray, infrared: np.ndarray) -> tuple[np.ndarray, float]:
    """The matrix from a whole `thermofield register` process with default options, and its wall-clock time."""
    with tempfile.TemporaryDirectory() as folder:
        fixed, moving, out = Path(folder) / "vi.png", Path(folder) / "ir.png", Path(folder) / "reg.json"
        cv2.imwrite(str(fixed), visible)
        cv2.imwrite(str(moving), infrared)
        command = [sys.executable, "-m", "services.cli.main", "register", "--fixed", str(fixed), "--moving",
                   str(moving), "--out", str(out)]
        start = time.perf_counter()
        subprocess.run(command, check=True, cwd=ROOT, capture_output=True,
                       env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
        seconds = time.perf_counter() - start
        return np.asarray(load_registration(out).matrix, dtype=float), seconds


METHODS = {"thermofield": thermofield_matrix, "thermofield NMI": thermofield_nmi_matrix,
           "SimpleITK Mattes": simpleitk_matrix}


def _timed(method, seconds: list[float]):
    """``method`` that appends the wall-clock time of each call to ``seconds``."""
    def timed(*images):
        start = time.perf_counter()
        matrix = method(*images)
        seconds.append(time.perf_counter() - start)
        return matrix
    return timed


def evaluate(numbers: list[int], seed: int, names: list[str], cli: bool, view: bool) -> list[dict]:
    rows = []
    methods = {name: METHODS[name] for name in names}
    for number in numbers:
        visible, infrared = load_pair(number)
        row = {"pair": number, "size": list(infrared.shape[::-1])}
        for name, method in methods.items():
            seconds: list[float] = []  # the whole image's, then the moved image's
            result = move_consistency(_timed(method, seconds), visible, infrared,
                                      np.random.default_rng([seed, number]), view=view)  # the same move for all
            row["view"] = list(result.moved_image.shape[::-1])
            row["known"] = 1.0 if result.moved_mask is None else float(result.moved_mask.mean())
            row[name] = {"consistency": result.consistency, "hand": result.from_hand, "seconds": seconds[1],
                         "unmoved": result.unmoved.tolist()}
        if cli:
            matrix, seconds = cli_matrix(visible, result.moved_image)
            reference = np.asarray(row["thermofield"]["unmoved"]) @ result.moved_to_infrared
            row["cli"] = {"seconds": seconds, "agrees": corner_error(reference, matrix, result.moved_image.shape[1],
                                                                     result.moved_image.shape[0])}
        rows.append(row)
        print(f"pair {number}: " + ", ".join(f"{name} {row[name]['consistency']:.3f} px" for name in methods),
              file=sys.stderr, flush=True)
    return rows


def _summary(values: list[float]) -> str:
    values = np.asarray(values)
    return (f"{np.median(values):.3f} | {np.percentile(values, 90):.3f} | {100.0 * np.mean(values < 1.0):.0f} % | "
            f"{values.max():.2f}")


def print_tables(rows: list[dict]) -> None:
    methods = [name for name in METHODS if all(name in row for row in rows)]
    print("| pair | size | moved image | known | " + " | ".join(f"{name} consistency (px) | {name} from hand (px)"
                                                              for name in methods) + " |")
    print("|---|---|---|---|" + "---|---|" * len(methods))
    for row in rows:
        cells = " | ".join(f"{row[name]['consistency']:.3f} | {row[name]['hand']:.2f}" for name in methods)
        print(f"| {row['pair']:02d} | {row['size'][0]}x{row['size'][1]} | {row['view'][0]}x{row['view'][1]} | "
              f"{100.0 * row['known']:.0f} % | {cells} |")
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
        ratios = [row["cli"]["seconds"] / row["SimpleITK Mattes"]["seconds"] for row in rows
                  if "SimpleITK Mattes" in row]
        print(f"\n`thermofield register` whole process: median {seconds:.2f} s per pair "
              f"(its matrix vs the in-process consistency reference: median {agrees:.3f} px)")
        if ratios:
            total = sum(row["cli"]["seconds"] for row in rows) / sum(row["SimpleITK Mattes"]["seconds"] for row in rows)
            print(f"per pair, the whole process's time over SimpleITK's in-process: median {np.median(ratios):.2f}, "
                  f"no slower on {sum(ratio <= 1.0 for ratio in ratios)} of {len(ratios)} pairs; all {len(ratios)} pairs' "
                  f"times summed: {total:.2f}")
            print("\n| pair | size | `thermofield register` whole process (s) | SimpleITK in-process (s) | ratio |")
            print("|---|---|---|---|---|")
            for row, ratio in zip(rows, ratios):
                print(f"| {row['pair']:02d} | {row['size'][0]}x{row['size'][1]} | {row['cli']['seconds']:.2f} | "
                      f"{row['SimpleITK Mattes']['seconds']:.2f} | {ratio:.2f} |")


def _edges(image: np.ndarray) -> np.ndarray:
    return cv2.Canny(cv2.GaussianBlur(image, (0, 0), 1.5), 30, 80) > 0


def _edge_overlay(visible: np.ndarray, infrared: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """The infrared image (dimmed) with its edges in red, the registered visible image's in green, both white."""
    height, width = infrared.shape
    warped = cv2.warpPerspective(visible, matrix, (width, height), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    infrared_edges, visible_edges = _edges(infrared), _edges(warped)
    picture = np.dstack([infrared // 3] * 3)
    picture[infrared_edges] = (0, 0, 255)
    picture[visible_edges] = (0, 255, 0)
    picture[infrared_edges & visible_edges] = (255, 255, 255)
    return picture


def figure(number: int) -> None:
    """Edges of one real pair at the hand alignment (left) and after registration (right)."""
    visible, infrared = load_pair(number)
    matrix = thermofield_matrix(visible, infrared)
    FIGURES.mkdir(parents=True, exist_ok=True)
    gap = np.full((infrared.shape[0], 8, 3), 255, np.uint8)
    cv2.imwrite(str(FIGURES / f"real_pair_{number:02d}_edges.png"),
                np.hstack([_edge_overlay(visible, infrared, np.eye(3)), gap, _edge_overlay(visible, infrared, matrix)]))


def moved_figure(number: int, seed: int) -> None:
    """The moved infrared image of one pair (what the registration found to carry no data, in blue) with the
    visible edges mapped by its registration (green; infrared edges red, white where both)."""
    visible, infrared = load_pair(number)
    moved, _, _ = moved_image(np.random.default_rng([seed, number]), infrared)
    picture = _edge_overlay(visible, moved, thermofield_matrix(visible, moved))
    mask = data_mask(moved)
    if mask is not None:
        picture[~mask] = (96, 0, 0)
    FIGURES.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(FIGURES / f"real_pair_{number:02d}_moved.png"), picture)


def objective_check(numbers: list[int], seed: int, view: bool) -> None:
    """Whether an inconsistency is the optimiser's or the objective's: each registration's objective value beside
    the value of the other registration carried over by the known move, on the moved and on the whole image."""
    print("| pair | consistency (px) | S(moved) at H1 | S(moved) at H0 S^-1 | S(whole) at H0 | S(whole) at H1 S |")
    print("|---|---|---|---|---|---|")
    for number in numbers:
        visible, infrared = load_pair(number)
        result = move_consistency(thermofield_matrix, visible, infrared, np.random.default_rng([seed, number]),
                                  view=view)
        unmoved, moved, moved_to_infrared = result.unmoved, result.moved, result.moved_to_infrared

        def value(infrared_image: np.ndarray, matrix: np.ndarray) -> float:
            return objective_value(visible, infrared_image, matrix, **_options(infrared_image, OPTIONS))

        print(f"| {number:02d} | {result.consistency:.3f} | "
              f"{value(result.moved_image, moved):.5f} | "
              f"{value(result.moved_image, unmoved @ moved_to_infrared):.5f} | "
              f"{value(infrared, unmoved):.5f} | {value(infrared, moved @ np.linalg.inv(moved_to_infrared)):.5f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--protocol", choices=("moved", "view"), default="moved",
                        help="move the infrared image on its own canvas, what the move brings in set to 0 (default), "
                             "or cut it to a view inside the original")
    parser.add_argument("--pairs", nargs="+", default=["all"],
                        help="'tuning' (odd numbers), 'reporting' (even), 'all' (default) or pair numbers")
    parser.add_argument("--option", nargs="+", default=[], metavar="KEY=VALUE",
                        help="keyword arguments of thermofield's register (shift=F: max_shift F times the smaller side)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", nargs="+", choices=list(METHODS), default=list(METHODS),
                        metavar="NAME", help=f"methods to run (default: all of {', '.join(METHODS)})")
    parser.add_argument("--no-cli", action="store_true")
    parser.add_argument("--figure", type=int, metavar="PAIR", help="write the before/after overlay of this pair")
    parser.add_argument("--moved-figure", type=int, metavar="PAIR",
                        help="write the registered overlay of this pair's moved infrared image and its mask")
    parser.add_argument("--rows-out", type=Path, help="also save the per-pair results as JSON")
    parser.add_argument("--objective-check", action="store_true",
                        help="print the objective at each registration and at the other one carried over by the move")
    parser.add_argument("--from-rows", type=Path, nargs="+",
                        help="print the tables of saved results (e.g. of runs on parts of the pairs) instead")
    args = parser.parse_args()
    if not args.no_cli and "thermofield" not in args.methods:
        parser.error("the command's run (without --no-cli) is compared with 'thermofield': run that method too")
    if not args.no_cli and args.option:
        parser.error("the command runs with default options: give --no-cli with --option")
    args.pairs = [number for item in args.pairs
                  for number in (SPLITS[item] if item in SPLITS else [int(item)])]
    for item in args.option:
        key, _, value = item.partition("=")
        OPTIONS[key] = value if key in ("metric", "preprocessing", "model") else float(value)
    if args.objective_check:
        objective_check(args.pairs, args.seed, args.protocol == "view")
        return
    if args.from_rows:
        rows = {}
        for path in args.from_rows:  # runs on parts of the pairs, or of the methods, merged pair by pair
            for row in json.loads(path.read_text()):
                rows.setdefault(row["pair"], {}).update(row)
        rows = [rows[number] for number in sorted(rows)]
    else:
        rows = evaluate(args.pairs, args.seed, args.methods, not args.no_cli, args.protocol == "view")
        if args.rows_out is not None:
            args.rows_out.write_text(json.dumps(rows))
    print_tables(rows)
    if args.figure is not None:
        figure(args.figure)
    if args.moved_figure is not None:
        moved_figure(args.moved_figure, args.seed)


if __name__ == "__main__":
    main()
