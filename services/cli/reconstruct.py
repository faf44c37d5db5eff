"""``thermofield reconstruct``: a structured-light capture directory to a point cloud PLY."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.structured_light import defaults


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        description="Decode the frames of a capture directory (sequence.json + camera frames) and "
                    "triangulate them with the rig's camera and projector into a binary PLY.",
    )
    parser.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    parser.add_argument("--captures", required=True, type=Path, help="directory with sequence.json and the frames")
    parser.add_argument("--out", required=True, type=Path, help="output point cloud (.ply)")
    parser.add_argument("--manifest", type=Path, default=None,
                        help="sequence manifest to use instead of DIR/sequence.json (captures of other software)")
    parser.add_argument("--max-indirect", type=float, default=defaults.MAX_INDIRECT, metavar="RATIO",
                        help="reject pixels whose inter-reflected light exceeds RATIO times their direct light, "
                             "from the fringe visibility (e.g. 0.33; default off: ambient light and glow lower the "
                             "visibility too)")
    parser.add_argument("--consistency", type=float, default=defaults.CONSISTENCY, metavar="FRACTION",
                        help="tolerance of the Gray code or coarser period against the unwrapped phase, as a fraction "
                             f"of the unwrapping margin (default {defaults.CONSISTENCY}; 0.5 for noisy coarse periods, e.g. 3 steps)")
    parser.add_argument("--camera", help="camera device name (default: the rig's only camera)")
    parser.add_argument("--projector", help="projector device name (default: the rig's only projector)")
    parser.add_argument("--saturation-level", type=float, default=None, metavar="GREY",
                        help="grey level at which the camera saturates (4095 for 12-bit frames in 16-bit files; "
                             "default the files' maximum, 255 or 65535)")
    parser.set_defaults(handler=_run)


def reconstruct_from_files(rig_path: Path, captures: Path, camera: str | None = None,
                           projector: str | None = None, manifest: Path | None = None,
                           saturation_level: float | None = None, max_indirect: float = defaults.MAX_INDIRECT,
                           consistency: float = defaults.CONSISTENCY):
    """Read a rig and a capture directory (or another program's, described by ``manifest``) and reconstruct;
    every error names the file at fault.

    The triangulation table is kept in the user's cache directory, so a second run with the same rig
    loads it instead of building it.
    """
    from services.formats.rig import load_rig
    from services.formats.sequence import read_capture
    from services.pipeline.reconstruct import reconstruct_capture
    from services.pipeline.tables import TriangulationTables, default_table_directory

    rig = load_rig(rig_path)
    sequence, frames = read_capture(captures, manifest)
    return rig, reconstruct_capture(frames=frames, sequence=sequence, rig=rig, camera=camera, projector=projector,
                                    saturation_level=saturation_level, max_indirect=max_indirect,
                                    consistency=consistency, tables=TriangulationTables(default_table_directory()),
                                    source=str(manifest or captures / "sequence.json")).cloud


def _run(args: argparse.Namespace) -> int:
    from services.formats.ply import write_cloud

    _, cloud = reconstruct_from_files(args.rig, args.captures, args.camera, args.projector, args.manifest,
                                      args.saturation_level, args.max_indirect, args.consistency)
    write_cloud(args.out, cloud, comments=[f"thermofield reconstruct of {args.captures.name}"])
    print(f"{args.out}: {len(cloud)} points")
    return 0
