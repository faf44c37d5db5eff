"""``thermofield register``: register an infrared image to a visible one (normalised gradient fields or MI)."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from services.errors import InputError
from services.formats.images import read_frame, write_png
from services.formats.registration import save_registration
from services.registration.models import MODELS
from services.registration.mutual_information import DEFAULT_BINS, DEFAULT_LOG_BASE
from services.registration.objective import METRICS
from services.registration.overlay import checkerboard_blend, fused_overlay
from services.registration.preprocess import PREPROCESSING
from services.registration.register import DEFAULT_METRIC, register as register_images


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "register",
        description="Find the matrix that maps infrared pixels to visible pixels by maximising the similarity of "
                    "their edges (normalised gradient fields, by default) or their mutual information: coarse "
                    "global search, multi-resolution refinement. A constant border that a move or a crop brought "
                    "into the infrared image is found and left out unless --moving-mask is given. The defaults "
                    "were chosen on real infrared/visible pairs (the odd TNO pairs; docs/registration.md). "
                    "Writes REG.json and optionally a fused overlay and a checkerboard blend.",
    )
    parser.add_argument("--fixed", required=True, type=Path, help="visible image (PNG, BMP, TIFF)")
    parser.add_argument("--moving", required=True, type=Path,
                        help="infrared image (PNG, BMP, TIFF of any bit depth, or 2-D .npy)")
    parser.add_argument("--moving-mask", type=Path, metavar="IMAGE",
                        help="the infrared pixels that have data: an image of the infrared image's size, non-zero "
                             "where they do (a lens housing, a text overlay or a border without data is left out); "
                             "replaces the default detection of a constant border connected to the image's edge")
    parser.add_argument("--model", choices=MODELS, default="similarity", help="geometric model (default %(default)s)")
    parser.add_argument("--out", required=True, type=Path, help="output registration (REG.json)")
    parser.add_argument("--overlay", type=Path, metavar="PNG", help="write a fused grey overlay (paper's Figure 12)")
    parser.add_argument("--checkerboard", type=Path, metavar="PNG", help="write a checkerboard blend")
    parser.add_argument("--preprocess", choices=PREPROCESSING,
                        help="intensity preprocessing (default: 'none' for ngf, which takes its own gradients: "
                             "'clahe' or 'paper' before it each lost a real tuning pair; 'gradient' for mi and nmi; "
                             "'paper' = invert + equalise)")
    parser.add_argument("--metric", choices=METRICS, default=DEFAULT_METRIC,
                        help="objective maximised: normalised gradient fields (ngf), normalised or plain mutual "
                             "information (default %(default)s: chosen on the tuning half of the real TNO pairs, "
                             "where it registered 13 of 13 consistently under 1 px and nmi 6 of 13)")
    parser.add_argument("--bins", type=int, default=DEFAULT_BINS, help="histogram bins per image (default %(default)s)")
    parser.add_argument("--log-base", type=float, default=DEFAULT_LOG_BASE,
                        help="logarithm base of the reported MI (default %(default)s: bits)")
    parser.add_argument("--scale", type=float,
                        help="nominal visible pixels per infrared pixel (default: fit the infrared image inside)")
    parser.add_argument("--max-shift", type=float, metavar="PX",
                        help="search range of the shift of the image centres along each axis, visible pixels "
                             "(default: 12%% of the infrared image's smaller side, scaled to visible pixels: 8%% to 20%% "
                             "did equally well on the real tuning pairs, and 12%% covers a 30 px move of a 256-pixel "
                             "image)")
    parser.add_argument("--max-angle", type=float, default=6.0, metavar="DEG",
                        help="search range of the rotation (default %(default)s)")
    parser.add_argument("--max-scale-change", type=float, default=0.12,
                        help="search range of the relative scale change (default %(default)s)")
    parser.set_defaults(handler=_run_register)


def _read_image(path: Path) -> np.ndarray:
    """A 2-D grey image from PNG/BMP/TIFF (any numeric type) or .npy, with errors that name the file."""
    suffix = path.suffix.lower()
    if suffix not in (".npy", ".tif", ".tiff"):
        return read_frame(path)
    if not path.is_file():
        raise InputError(f"{path}: image file is missing")
    import tifffile  # only for TIFF and .npy inputs: its import costs about 0.1 s of every command's start

    try:
        image = np.load(path, allow_pickle=False) if suffix == ".npy" else tifffile.imread(path)
    except (OSError, ValueError, tifffile.TiffFileError) as error:
        raise InputError(f"{path}: cannot read the image ({error})") from None
    if image.ndim != 2 or not np.issubdtype(image.dtype, np.number):
        raise InputError(f"{path}: the image must be a 2-D numeric array; got {image.dtype} of shape {image.shape}")
    if not np.isfinite(image).any():
        raise InputError(f"{path}: the image has no finite pixel")
    return image


def _read_mask(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    """The mask of the infrared pixels that have data (non-zero), checked against the infrared image's shape."""
    mask = _read_image(path) != 0
    if mask.shape != shape:
        raise InputError(f"--moving-mask {path}: the mask is {mask.shape[1]}x{mask.shape[0]} pixels, the infrared "
                         f"image {shape[1]}x{shape[0]}")
    if not mask.any():
        raise InputError(f"--moving-mask {path}: the mask is zero everywhere, so no infrared pixel has data")
    return mask


def _run_register(args: argparse.Namespace) -> int:
    cv2.setNumThreads(1)  # OpenCV's worker threads gain no wall time on images this small, only spin (measured)
    for option in ("out", "overlay", "checkerboard"):
        path = getattr(args, option)
        if path is None:
            continue
        if option != "out" and path.suffix.lower() != ".png":
            raise InputError(f"--{option} {path}: the picture must be a .png file")
        if not path.parent.is_dir():
            raise InputError(f"--{option} {path}: the directory {path.parent} does not exist")
    fixed = _read_image(args.fixed)
    moving = _read_image(args.moving)
    mask = None if args.moving_mask is None else _read_mask(args.moving_mask, moving.shape)
    try:
        result = register_images(
            fixed, moving, args.model, preprocessing=args.preprocess, bins=args.bins, log_base=args.log_base,
            metric=args.metric, scale=args.scale, max_shift=args.max_shift, max_angle=args.max_angle,
            max_scale_change=args.max_scale_change, moving_mask=mask,
        )
    except ValueError as error:
        raise InputError(f"{args.fixed} + {args.moving}: {error}") from None
    save_registration(result, args.out)
    if args.overlay is not None:
        write_png(args.overlay, fused_overlay(fixed, moving, result.matrix))
    if args.checkerboard is not None:
        write_png(args.checkerboard, checkerboard_blend(fixed, moving, result.matrix))
    print(f"{args.out}: {result.model}, MI {result.mi:.3f} (base {result.log_base:g}, {result.bins} bins), "
          f"NMI {result.nmi:.3f}")
    return 0
