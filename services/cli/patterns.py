"""``thermofield patterns``: write the default projector sequence as PNG frames and ``sequence.json``."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from services.errors import InputError
from services.formats.files import output_directory
from services.formats.images import write_png
from services.formats.sequence import save_sequence
from services.structured_light.patterns import DEFAULT_PERIOD, DEFAULT_STEPS, generate_sequence


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "patterns",
        description="Write the default structured-light sequence (white, black, complementary Gray code and "
                    "N-step phase shifting) as one 8-bit PNG per frame plus DIR/sequence.json.",
    )
    parser.add_argument("--projector", required=True, metavar="WIDTHxHEIGHT", help="projector size, e.g. 1280x800")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="output directory (created if needed)")
    parser.add_argument("--period", type=float, default=DEFAULT_PERIOD,
                        help=f"phase period in projector pixels (default {DEFAULT_PERIOD})")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS,
                        help=f"number of phase steps, at least 3 (default {DEFAULT_STEPS})")
    parser.add_argument("--axes", choices=("x", "y", "xy"), default="x",
                        help="code projector columns (x), rows (y) or both (default x)")
    parser.set_defaults(handler=_run)


def _projector_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or int(match[1]) < 1 or int(match[2]) < 1:
        raise InputError(f"--projector: expected WIDTHxHEIGHT with positive integers, e.g. 1280x800; got {text!r}")
    return int(match[1]), int(match[2])


def _run(args: argparse.Namespace) -> int:
    width, height = _projector_size(args.projector)
    if not args.period >= 2:
        raise InputError(f"--period: the phase period must be at least 2 projector pixels; got {args.period:g}")
    if args.steps < 3:
        raise InputError(f"--steps: phase shifting needs at least 3 steps; got {args.steps}")
    sequence, patterns = generate_sequence(width, height, axes=args.axes, period=args.period, steps=args.steps)
    output_directory(args.out)
    for frame, image in zip(sequence.frames, patterns):
        write_png(args.out / frame.file, image)
    save_sequence(sequence, args.out)
    print(f"{args.out}: {len(sequence.frames)} frames for a {width}x{height} projector and sequence.json")
    return 0
