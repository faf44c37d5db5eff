"""``thermofield rig import``: another program's calibration file to our rig file."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from services.errors import InputError
from services.formats.foreign_rig import FOREIGN_FORMATS, import_rig
from services.formats.rig import save_rig

_KINDS = ("camera", "projector", "thermal")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("rig")
    topics = parser.add_subparsers(dest="rig_command", required=True, metavar="ACTION")
    importer = topics.add_parser(
        "import",
        help="convert a foreign two-device calibration (SLStudio, cv2.stereoCalibrate) to a rig file",
        description="Read an OpenCV FileStorage calibration (XML or YAML) and write a rig file whose world "
                    "frame is the first device's (the camera for slstudio, device 1 for opencv-stereo). "
                    "Conventions: docs/rig-file.md.",
    )
    importer.add_argument("file", type=Path, help="the calibration file (XML or YAML)")
    importer.add_argument("--format", required=True, choices=FOREIGN_FORMATS, dest="file_format",
                          help="slstudio: calibration.xml (Kc, kc, Kp, kp, Rp, Tp); opencv-stereo: K1, D1, K2, D2, "
                               "R, T from cv2.stereoCalibrate")
    importer.add_argument("--out", required=True, type=Path, help="rig JSON to write")
    importer.add_argument("--names", nargs=2, default=("camera", "projector"), metavar=("FIRST", "SECOND"),
                          help="device names in the rig (default: camera projector)")
    importer.add_argument("--kinds", nargs=2, default=("camera", "projector"), choices=_KINDS,
                          metavar=("FIRST", "SECOND"), help=f"device kinds, each one of {', '.join(_KINDS)} "
                                                            "(default: camera projector)")
    importer.add_argument("--sizes", nargs=2, default=None, metavar=("W1xH1", "W2xH2"),
                          help="image sizes, for opencv-stereo files that do not store imageSize1/imageSize2")
    importer.set_defaults(handler=_run_import)


def _size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match or int(match[1]) < 1 or int(match[2]) < 1:
        raise InputError(f"--sizes: expected WIDTHxHEIGHT with positive integers, e.g. 1688x1352; got {text!r}")
    return int(match[1]), int(match[2])


def _run_import(args: argparse.Namespace) -> int:
    sizes = (None, None) if args.sizes is None else tuple(_size(text) for text in args.sizes)
    rig = import_rig(args.file, args.file_format, names=tuple(args.names), kinds=tuple(args.kinds), sizes=sizes)
    save_rig(rig, args.out)
    first, second = args.names
    baseline = float(((rig.devices[second].R.T @ rig.devices[second].t) ** 2).sum() ** 0.5)
    print(f"{args.out}: {first} ({args.kinds[0]}, world frame) and {second} ({args.kinds[1]}), "
          f"baseline {baseline:.2f} mm")
    return 0
