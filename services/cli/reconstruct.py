"""``thermofield reconstruct``: a structured-light capture directory to a point cloud PLY."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.errors import InputError
from services.formats.ply import write_cloud
from services.formats.rig import load_rig
from services.formats.sequence import read_capture
from services.structured_light.decode import decode
from services.structured_light.reconstruct import reconstruct_points


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        help="decode a structured-light capture and triangulate a point cloud",
        description="Decode the frames of a capture directory (sequence.json + camera frames) and "
                    "triangulate them with the rig's camera and projector into a binary PLY.",
    )
    parser.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    parser.add_argument("--captures", required=True, type=Path, help="directory with sequence.json and the frames")
    parser.add_argument("--out", required=True, type=Path, help="output point cloud (.ply)")
    parser.add_argument("--manifest", type=Path, default=None,
                        help="sequence manifest to use instead of DIR/sequence.json (captures of other software)")
    parser.add_argument("--max-indirect", type=float, default=float("inf"), metavar="RATIO",
                        help="reject pixels whose inter-reflected light exceeds RATIO times their direct light, "
                             "from the fringe visibility (e.g. 0.33; default off: ambient light and glow lower the "
                             "visibility too)")
    parser.add_argument("--consistency", type=float, default=0.25, metavar="FRACTION",
                        help="tolerance of the Gray code or coarser period against the unwrapped phase, as a fraction "
                             "of the unwrapping margin (default 0.25; 0.5 for noisy coarse periods, e.g. 3 steps)")
    parser.add_argument("--camera", help="camera device name (default: the rig's only camera)")
    parser.add_argument("--projector", help="projector device name (default: the rig's only projector)")
    parser.add_argument("--saturation-level", type=float, default=None, metavar="GREY",
                        help="grey level at which the camera saturates (4095 for 12-bit frames in 16-bit files; "
                             "default the files' maximum, 255 or 65535)")
    parser.set_defaults(handler=_run)


def reconstruct_from_files(rig_path: Path, captures: Path, camera_name: str | None = None,
                           projector_name: str | None = None, manifest: Path | None = None,
                           saturation_level: float | None = None, max_indirect: float = float("inf"),
                           consistency: float = 0.25) -> dict[str, np.ndarray]:
    """Read a rig and a capture directory and reconstruct; every error names the file at fault."""
    rig = load_rig(rig_path)
    _, camera = rig.device(camera_name, "camera")
    _, projector = rig.device(projector_name, "projector")
    sequence, frames = read_capture(captures, manifest)
    if (sequence.projector.width, sequence.projector.height) != projector.size:
        raise InputError(
            f"{captures / 'sequence.json'}: the manifest is for a {sequence.projector.width}x"
            f"{sequence.projector.height} projector but the rig's projector is {projector.width}x{projector.height}"
        )
    if (frames.shape[2], frames.shape[1]) != camera.size:
        raise InputError(
            f"{captures}: frames are {frames.shape[2]}x{frames.shape[1]} but the rig's camera is "
            f"{camera.width}x{camera.height}"
        )
    if saturation_level is not None and not 0 < saturation_level <= np.iinfo(frames.dtype).max:
        raise InputError(f"--saturation-level must be in (0, {np.iinfo(frames.dtype).max}] for "
                         f"{frames.dtype} frames; got {saturation_level:g}")
    if not max_indirect > 0:
        raise InputError(f"--max-indirect must be a positive ratio; got {max_indirect}")
    if not 0 <= consistency <= 1:
        raise InputError(f"--consistency must be between 0 and 1; got {consistency}")
    cloud = reconstruct_points(frames, sequence, camera, projector, saturation_level=saturation_level,
                               max_indirect=max_indirect, consistency=consistency)
    if len(cloud["x"]) == 0:
        counts = np.bincount(decode(frames, sequence).rejection.ravel())
        reasons = ", ".join(f"code {code}: {count} px" for code, count in enumerate(counts) if count)
        raise InputError(
            f"{captures}: no point could be reconstructed (rejected pixels by reason {reasons}; see "
            "docs/sequence-manifest.md for the codes); check exposure, the manifest and the rig"
        )
    return cloud


def _run(args: argparse.Namespace) -> int:
    cloud = reconstruct_from_files(args.rig, args.captures, args.camera, args.projector, args.manifest,
                                   args.saturation_level, args.max_indirect, args.consistency)
    write_cloud(args.out, cloud, comments=[f"thermofield reconstruct of {args.captures.name}"])
    print(f"{args.out}: {len(cloud['x'])} points")
    return 0
