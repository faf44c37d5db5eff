"""``thermofield fuse`` and ``thermofield field``: point clouds plus thermal frames to 3D temperature fields."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.thermal import add_condition_arguments, condition_overrides
from services.errors import InputError
from services.fusion.fuse import DEFAULT_MAX_VIEW_ANGLE_DEG


def _add_thermal_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--thermal", required=True, nargs="+", action="extend", metavar="[NAME=]FRAME",
                        help="thermal frame(s): FLIR radiometric JPEG, float TIFF/.npy in degrees C, 16-bit "
                             "PNG/TIFF in centikelvin, or counts with a sidecar JSON (see docs/thermal-formats.md); "
                             "NAME=FRAME names the rig's thermal device that took it (repeatable: one frame per "
                             "thermal camera of a station)")
    parser.add_argument("--thermal-device", nargs="+", metavar="NAME",
                        help="thermal device of the rig: one name for all frames or one per frame "
                             "(default: the rig's only thermal device)")
    add_condition_arguments(parser)
    parser.add_argument("--max-view-angle", type=float, default=DEFAULT_MAX_VIEW_ANGLE_DEG, metavar="DEG",
                        help="ignore a view that sees a point more obliquely than this (default %(default)s)")
    parser.add_argument("--out", required=True, type=Path, help="output temperature field (.ply)")


def register(subparsers: argparse._SubParsersAction) -> None:
    fuse = subparsers.add_parser(
        "fuse",
        description="Project every point of a PLY cloud into the rig's thermal camera(s), keep the points "
                    "it sees (z-buffer), sample the frames and write the cloud with temperature, "
                    "view_angle and colour-mapped RGB.",
    )
    fuse.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    fuse.add_argument("--cloud", required=True, type=Path, help="point cloud (.ply with x, y, z)")
    _add_thermal_arguments(fuse)
    fuse.set_defaults(handler=_run_fuse)

    field = subparsers.add_parser(
        "field",
        description="Reconstruct a capture directory (as `thermofield reconstruct`) and fuse the thermal "
                    "frames onto the cloud (as `thermofield fuse`), in one step. A station's capture (one "
                    "sub-directory per head of the rig) is reconstructed head by head and merged first; give "
                    "one frame per thermal camera, --thermal NAME=FRAME (see docs/station.md).",
    )
    field.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    field.add_argument("--captures", required=True, type=Path,
                       help="directory with sequence.json and the camera frames, or a station's with one such "
                            "sub-directory per head")
    field.add_argument("--camera", help="camera device name (default: the rig's only camera)")
    field.add_argument("--projector", help="projector device name (default: the rig's only projector)")
    _add_thermal_arguments(field)
    field.set_defaults(handler=_run_field)


def _named_frames(rig, values: list[str]) -> tuple[list[Path], list[str] | None]:
    """``--thermal`` values as paths, and their device names when every value is ``NAME=FRAME`` with NAME a
    thermal device of the rig (None when none is); a mix is refused."""
    thermal = {name for name, device in rig.devices.items() if device.kind == "thermal"}
    named = [value.partition("=") for value in values]
    is_named = [separator == "=" and name in thermal for name, separator, _ in named]
    if not any(is_named):
        return [Path(value) for value in values], None
    if not all(is_named):
        plain = [value for value, flag in zip(values, is_named) if not flag]
        raise InputError(f"--thermal: name the thermal device of every frame or of none (NAME=FRAME, NAME one of "
                         f"{sorted(thermal)}); {plain} name none")
    return [Path(path) for _, _, path in named], [name for name, _, _ in named]


def _read_thermal(rig, values: list[str], device_names: list[str] | None, overrides):
    """The thermal frames, each with the name of the rig's thermal device that took it."""
    from services.formats.thermal import read_thermal_frame

    frames, named = _named_frames(rig, values)
    if named is not None and device_names:
        raise InputError("--thermal-device: the frames name their devices already (NAME=FRAME)")
    names = named or device_names or [None]
    if len(names) not in (1, len(frames)):
        raise InputError(
            f"--thermal-device takes one name or one per frame; got {len(names)} names for {len(frames)} frames"
        )
    named = []
    for path, name in zip(frames, names * len(frames) if len(names) == 1 else names):
        device_name, device = rig.device(name, "thermal")
        named.append((device_name, read_thermal_frame(path, device.size, overrides)))
    return named


def _fuse_and_write(rig, cloud, args: argparse.Namespace, source: str) -> int:
    import numpy as np

    from services.formats.ply import write_cloud
    from services.pipeline.field import fuse_field

    if not 0.0 < args.max_view_angle < 90.0:
        raise InputError(f"--max-view-angle must be in (0, 90) degrees; got {args.max_view_angle}")
    thermal = _read_thermal(rig, args.thermal, args.thermal_device, condition_overrides(args))
    field = fuse_field(cloud=cloud, rig=rig, thermal=thermal, max_view_angle_deg=args.max_view_angle, source=source)
    write_cloud(args.out, field, comments=[f"thermofield temperature field of {source}",
                                           "temperature in degrees C (nan: unseen), view_angle in degrees"])
    temperature = field["temperature"]
    seen = temperature[np.isfinite(temperature)]
    summary = (f"{len(seen)} of {len(temperature)} points have a temperature"
               + (f", {seen.min():.1f} to {seen.max():.1f} C" if len(seen) else ""))
    print(f"{args.out}: {summary}")
    return 0


def _run_fuse(args: argparse.Namespace) -> int:
    from services.formats.ply import read_cloud
    from services.formats.rig import load_rig

    rig = load_rig(args.rig)
    return _fuse_and_write(rig, read_cloud(args.cloud), args, str(args.cloud))


def _run_field(args: argparse.Namespace) -> int:
    from services.cli.reconstruct import (merge_summary, reconstruct_from_files, station_capture_of,
                                          station_from_files)

    rig, station = station_capture_of(args)
    if station:
        merged = station_from_files(rig, args.captures)
        print(f"merged {len(merged.cloud)} points from {len(rig.heads)} heads\n{merge_summary(merged.report)}")
        return _fuse_and_write(rig, merged.cloud, args, args.captures.name)
    rig, cloud = reconstruct_from_files(args.rig, args.captures, args.camera, args.projector)
    return _fuse_and_write(rig, cloud, args, args.captures.name)
