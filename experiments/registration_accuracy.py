"""Registration accuracy on pairs with known infrared-to-visible matrices (tables and figures of docs/registration.md).

Pairs: (a) rendered scenes, 1024x768 visible / 320x256 infrared of hot and
cold parts, each band with its own intensity mapping; (b) the real visible
photographs of ../shared/data/opencv-chessboard (640x480) with a synthetic
infrared modality change (negative, gamma 0.6, heat blobs, blur, 320x256,
noise). Every pair is moved by a random similarity: centre shift up to 40 px
per axis, rotation up to 5 degrees, scale change up to 10 %.

A third source, (c) the simulator's calibration board (services.simulation.boards)
seen by a 1024x768 visible camera and, as the paper's hollowed board before a
heater, by a 320x256 infrared camera at the same centre (pan/tilt up to 2
degrees, roll up to 5, focal length +-10 %; the true matrix is the rotation
homography K_v R^T K_ir^-1), is reported on its own: a periodic pattern whose
border inverts between the bands.

Usage: .venv/bin/python experiments/registration_accuracy.py [--pairs-per-source 50] [--seed 0]
       [--sections similarity variants models boards] [--variants none:ngf ...]
Prints Markdown tables; writes figures to docs/figures/registration/.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from scipy.spatial.transform import Rotation  # noqa: E402

from services.formats.board import ChessboardSpec  # noqa: E402
from services.registration.models import apply_homography, corner_error  # noqa: E402
from services.registration.overlay import checkerboard_blend, fused_overlay  # noqa: E402
from services.registration.preprocess import preprocess  # noqa: E402
from services.registration.register import DEFAULT_METRIC, DEFAULT_PREPROCESSING, register  # noqa: E402
from services.registration.synthetic_pairs import (  # noqa: E402
    infrared_from_visible,
    random_transform,
    render_scene_pair,
)
from services.simulation.boards import render_board  # noqa: E402

CHESSBOARD_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "opencv-chessboard"  # shared/ beside the clone
FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures" / "registration"
INFRARED_SIZE = (320, 256)


def scene_pairs(rng: np.random.Generator, count: int):
    for _ in range(count):
        matrix = random_transform(rng, INFRARED_SIZE, (1024, 768), 3.0)
        visible, infrared = render_scene_pair(rng, matrix)
        yield "scene", visible, infrared, matrix, None


def photograph_pairs(rng: np.random.Generator, count: int):
    paths = sorted(CHESSBOARD_DIR.glob("*.jpg"))
    for index in range(count):
        visible = cv2.imread(str(paths[index % len(paths)]), cv2.IMREAD_GRAYSCALE)
        matrix = random_transform(rng, INFRARED_SIZE, (visible.shape[1], visible.shape[0]), 1.8)
        yield "photograph", visible, infrared_from_visible(rng, visible, matrix, INFRARED_SIZE), matrix, 1.8


def board_pairs(rng: np.random.Generator, count: int):
    board = ChessboardSpec(type="chessboard", inner_corners=(9, 6), square_mm=30.0)
    visible_k = np.array([[1100.0, 0.0, 511.5], [0.0, 1100.0, 383.5], [0.0, 0.0, 1.0]])
    for _ in range(count):
        focal = 1100.0 / 3.0 * (1.0 + rng.uniform(-0.1, 0.1))
        infrared_k = np.array([[focal, 0.0, 159.5], [0.0, focal, 127.5], [0.0, 0.0, 1.0]])
        rotation = Rotation.from_euler("xyz", rng.uniform(-20.0, 20.0, 3) * [1.0, 1.0, 0.5], degrees=True).as_matrix()
        translation = np.array([0.0, 0.0, 650.0]) - rotation @ np.array([150.0, 105.0, 0.0])
        relative = Rotation.from_euler("xyz", rng.uniform(-1.0, 1.0, 3) * [2.0, 2.0, 5.0], degrees=True).as_matrix()
        visible = render_board(board, visible_k, np.zeros(5), rotation, translation, (1024, 768),
                               blur_sigma=0.7, noise_sigma=2.0, rng=rng)
        infrared = render_board(board, infrared_k, np.zeros(5), relative @ rotation, relative @ translation,
                                INFRARED_SIZE, modality="infrared", blur_sigma=0.8, noise_sigma=100.0,
                                bit_depth=16, rng=rng)
        matrix = visible_k @ relative.T @ np.linalg.inv(infrared_k)
        yield "board", visible, infrared, matrix / matrix[2, 2], None


def _summary(errors: list[float]) -> str:
    errors = np.asarray(errors)
    return (f"{len(errors)} | {np.median(errors):.3f} | {np.percentile(errors, 90):.3f} | "
            f"{100.0 * np.mean(errors < 1.0):.0f} % | {errors.max():.2f}")


def run(pairs: list, model: str, preprocessing: str | None, metric: str) -> dict[str, list[float]]:
    errors: dict[str, list[float]] = {"scene": [], "photograph": [], "seconds": []}
    for source, visible, infrared, truth, scale in pairs:
        start = time.perf_counter()
        result = register(visible, infrared, model, preprocessing=preprocessing, metric=metric, scale=scale)
        errors["seconds"].append(time.perf_counter() - start)
        errors[source].append(corner_error(truth, result.matrix, *INFRARED_SIZE))
    return errors


def _at_most_640_wide(image: np.ndarray) -> np.ndarray:
    factor = 640.0 / image.shape[1]
    return image if factor >= 1.0 else cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)


def _preprocessing_figure(visible: np.ndarray, infrared: np.ndarray, path: Path) -> None:
    """Visible and infrared images raw, as the paper preprocesses them, and as gradient magnitude (cf. Figure 11)."""
    figure, axes = plt.subplots(2, 3, figsize=(10, 5.2))
    for row, (label, image, invert) in enumerate((("visible", visible, True), ("infrared", infrared, False))):
        panels = (("raw", preprocess(image, "none")), ("paper: invert + equalise" if invert else "paper: equalise",
                  preprocess(image, "paper", invert=invert)), ("gradient magnitude", preprocess(image, "gradient")))
        for axis, (title, panel) in zip(axes[row], panels):
            axis.imshow(panel, cmap="gray", vmin=0.0, vmax=1.0)
            axis.set_title(f"{label}: {title}", fontsize=9)
            axis.axis("off")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def _figures(pairs: list, errors: dict[str, list[float]]) -> None:
    FIGURES.mkdir(parents=True, exist_ok=True)
    figure, axis = plt.subplots(figsize=(6, 3.5))
    for source in ("scene", "photograph"):
        values = np.sort(errors[source])
        axis.step(values, np.arange(1, len(values) + 1) / len(values), where="post", label=source)
    axis.axvline(0.3, color="grey", linestyle=":", label="0.3 px (median target)")
    axis.axvline(1.0, color="grey", linestyle="--", label="1 px")
    axis.set_xscale("log")
    axis.set_xlabel("corner error (visible pixels)")
    axis.set_ylabel("fraction of pairs")
    axis.set_title(f"Similarity registration, default settings ({DEFAULT_METRIC})")
    axis.legend(loc="lower right")
    figure.tight_layout()
    figure.savefig(FIGURES / "corner_error_cdf.png", dpi=120)
    plt.close(figure)
    for source, visible, infrared, truth, scale in pairs[:1] + [pair for pair in pairs if pair[0] == "photograph"][:1]:
        result = register(visible, infrared, "similarity", scale=scale)
        pictures = {
            "infrared": cv2.equalizeHist(cv2.normalize(infrared, None, 0, 255, cv2.NORM_MINMAX, cv2.CV_8U)),
            "visible": visible,
            "overlay": fused_overlay(visible, infrared, result.matrix),
            "checkerboard": checkerboard_blend(visible, infrared, result.matrix),
        }
        for name, picture in pictures.items():
            cv2.imwrite(str(FIGURES / f"{source}_{name}.png"), _at_most_640_wide(picture))
        _preprocessing_figure(visible, infrared, FIGURES / f"{source}_preprocessing.png")


SECTIONS = ["similarity", "variants", "models", "boards"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs-per-source", type=int, default=50)
    parser.add_argument("--variant-pairs", type=int, default=12, help="pairs per source for the variant tables")
    parser.add_argument("--board-pairs", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sections", nargs="+", default=SECTIONS, choices=SECTIONS)
    parser.add_argument("--variants", nargs="+", default=VARIANTS, choices=VARIANTS, metavar="PRE:METRIC",
                        help="preprocessing:metric pairs of the variants table (default: all)")
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    pairs = list(scene_pairs(rng, args.pairs_per_source)) + list(photograph_pairs(rng, args.pairs_per_source))
    if "similarity" in args.sections:
        _similarity_section(pairs)
    variants = ([pair for pair in pairs if pair[0] == "scene"][:args.variant_pairs]
                + [pair for pair in pairs if pair[0] == "photograph"][:args.variant_pairs])
    if "variants" in args.sections:
        _variant_section(variants, args.variants)
    if "models" in args.sections:
        _model_section(variants)
    if "boards" in args.sections:
        _board_section(list(board_pairs(rng, args.board_pairs)))


def _similarity_section(pairs: list) -> None:
    print(f"## Similarity model: the default ({DEFAULT_METRIC}, preprocessing "
          f"{DEFAULT_PREPROCESSING[DEFAULT_METRIC]}) and gradient-magnitude NMI\n")
    print("| method | pairs | n | median (px) | 90th pct (px) | under 1 px | max (px) | median time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for label, preprocessing, metric in ((f"default ({DEFAULT_METRIC})", None, DEFAULT_METRIC),
                                         ("gradient, nmi", "gradient", "nmi")):
        errors = run(pairs, "similarity", preprocessing, metric)
        seconds = np.median(errors["seconds"])
        for source, name in (("scene", "rendered scenes"), ("photograph", "real photographs")):
            print(f"| {label} | {name} | {_summary(errors[source])} | {seconds:.2f} |")
        print(f"| {label} | all | {_summary(errors['scene'] + errors['photograph'])} | {seconds:.2f} |")
        if metric == DEFAULT_METRIC:
            _figures(pairs, errors)
    print()


VARIANTS = ["paper:mi", "paper:nmi", "clahe:nmi", "gradient:mi", "gradient:nmi", "none:ngf"]


def _variant_section(variants: list, names: list[str]) -> None:
    print("## Preprocessing and metric (similarity model)\n")
    print("| preprocessing | metric | source | n | median (px) | 90th pct (px) | under 1 px | max (px) |")
    print("|---|---|---|---|---|---|---|---|")
    for preprocessing, metric in (name.split(":") for name in names):
        result = run(variants, "similarity", preprocessing, metric)
        for source in ("scene", "photograph"):
            print(f"| {preprocessing} | {metric} | {source} | {_summary(result[source])} |")


def _model_section(variants: list) -> None:
    print("\n## Models (gradient, NMI) on the same similarity-moved pairs\n")
    print("| model | source | n | median (px) | 90th pct (px) | under 1 px | max (px) | median time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for model in ("similarity", "affine", "homography"):
        result = run(variants, model, "gradient", "nmi")
        for source in ("scene", "photograph"):
            print(f"| {model} | {source} | {_summary(result[source])} | {np.median(result['seconds']):.2f} |")



def _board_section(pairs: list) -> None:
    print("\n## Simulator calibration board (visible board vs hollowed board before a heater)\n")
    print("| model | preprocessing | pair | corner error (px) | centre offset (px) |")
    print("|---|---|---|---|---|")
    centre = np.array([[(INFRARED_SIZE[0] - 1) / 2.0, (INFRARED_SIZE[1] - 1) / 2.0]])
    for index, (_, visible, infrared, truth, _) in enumerate(pairs):
        for model, preprocessing in (("similarity", "gradient"), ("homography", "gradient"), ("similarity", "paper")):
            matrix = register(visible, infrared, model, preprocessing=preprocessing, metric="nmi").matrix
            offset = (apply_homography(matrix, centre) - apply_homography(truth, centre))[0]
            print(f"| {model} | {preprocessing} | {index} | {corner_error(truth, matrix, *INFRARED_SIZE):.2f} | "
                  f"({offset[0]:.1f}, {offset[1]:.1f}) |")


if __name__ == "__main__":
    main()
