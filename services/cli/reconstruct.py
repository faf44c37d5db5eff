"""``thermofield reconstruct``: a structured-light capture directory to a point cloud PLY."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.structured_light import defaults


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "reconstruct",
        description="Decode the frames of a capture directory (sequence.json + camera frames) and "
                    "triangulate them with the rig's camera and projector into a binary PLY. With a station's "
                    "rig (several heads) and a capture directory holding one sub-directory per head (named as "
                    "in the rig), every head is reconstructed and the clouds merged into one, each point with "
                    "its head's index (see docs/station.md).",
    )
    parser.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    parser.add_argument("--captures", required=True, type=Path,
                        help="directory with sequence.json and the frames, or a station's with one such "
                             "sub-directory per head")
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


def station_from_files(rig, captures: Path, saturation_level: float | None = None):
    """Reconstruct every head of a station capture directory (one sub-directory per head of ``rig``) and merge
    the clouds (:func:`services.pipeline.station.reconstruct_station`)."""
    from services.formats.station_capture import read_station_capture
    from services.pipeline.station import reconstruct_station
    from services.pipeline.tables import TriangulationTables, default_table_directory

    return reconstruct_station(heads=read_station_capture(captures, rig), rig=rig, saturation_level=saturation_level,
                               tables=TriangulationTables(default_table_directory()), source=str(captures))


def station_capture_of(args: argparse.Namespace):
    """The rig, and whether ``--captures`` is a station capture (one sub-directory per head) for it; the options
    that pick one camera and projector do not apply to a station capture."""
    from services.errors import InputError
    from services.formats.rig import load_rig
    from services.formats.station_capture import is_station_capture

    rig = load_rig(args.rig)
    station = is_station_capture(args.captures, rig)
    if station:
        given = [option for option, value in (("--camera", args.camera), ("--projector", args.projector),
                                              ("--manifest", getattr(args, "manifest", None))) if value]
        if given:
            raise InputError(f"{args.captures}: a station capture (one sub-directory per head) takes each head's "
                             f"camera and projector from the rig; {', '.join(given)} {'does' if len(given) == 1 else 'do'} not apply")
    return rig, station


def merge_summary(report) -> str:
    """One line per head (points measured and kept, pose correction) and per overlapping pair (residual)."""
    lines = []
    for name, measured, kept, correction in zip(report.heads, report.measured_points, report.kept_points,
                                                report.corrections):
        change = (f"pose corrected by {correction.translation_mm:.3f} mm, {correction.rotation_deg:.4f} deg"
                  if correction.applied else f"pose kept ({correction.reason or 'the reference'})")
        if correction.applied and correction.translation_mm == 0 and correction.rotation_deg == 0:
            change = "pose kept (the reference)"
        lines.append(f"  {name}: {measured} points, {kept} kept; {change}")
    for residual in report.residuals:
        lines.append(f"  overlap {residual.first}/{residual.second}: {residual.points} points, residual "
                     f"{residual.patch_rms_mm:.4f} mm RMS over {4:g} mm patches ({residual.rms_mm:.4f} mm per point)")
    return "\n".join(lines)


def _run(args: argparse.Namespace) -> int:
    from services.formats.ply import write_cloud

    rig, station = station_capture_of(args)
    if station:
        merged = station_from_files(rig, args.captures, args.saturation_level)
        write_cloud(args.out, merged.cloud, comments=[f"thermofield reconstruct of the station capture "
                                                      f"{args.captures.name}", "head: index into the rig's heads"])
        print(f"{args.out}: {len(merged.cloud)} points from {len(rig.heads)} heads\n{merge_summary(merged.report)}")
        return 0
    _, cloud = reconstruct_from_files(args.rig, args.captures, args.camera, args.projector, args.manifest,
                                      args.saturation_level, args.max_indirect, args.consistency)
    write_cloud(args.out, cloud, comments=[f"thermofield reconstruct of {args.captures.name}"])
    print(f"{args.out}: {len(cloud)} points")
    return 0
