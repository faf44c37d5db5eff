"""``thermofield fuse`` and ``thermofield field``: point clouds plus thermal frames to 3D temperature fields."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.cli.reconstruct import reconstruct_from_files
from services.errors import InputError
from services.formats.ply import read_cloud, write_cloud
from services.formats.rig import Rig, load_rig
from services.formats.thermal import read_thermal_frame
from services.fusion.field import temperature_field
from services.fusion.fuse import DEFAULT_MAX_VIEW_ANGLE_DEG, ThermalView
from services.geometry.camera import camera_center


def _add_thermal_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--thermal", required=True, nargs="+", type=Path, metavar="FRAME",
                        help="thermal frame(s): float TIFF/.npy in degrees C, 16-bit PNG/TIFF in centikelvin, "
                             "or raw counts with a sidecar JSON (see docs/temperature-field.md)")
    parser.add_argument("--thermal-device", nargs="+", metavar="NAME",
                        help="thermal device of the rig: one name for all frames or one per frame "
                             "(default: the rig's only thermal device)")
    parser.add_argument("--emissivity", type=float,
                        help="object emissivity in (0, 1] (default: the frames' sidecars, else 1)")
    parser.add_argument("--max-view-angle", type=float, default=DEFAULT_MAX_VIEW_ANGLE_DEG, metavar="DEG",
                        help="ignore a view that sees a point more obliquely than this (default %(default)s)")
    parser.add_argument("--out", required=True, type=Path, help="output temperature field (.ply)")


def register(subparsers: argparse._SubParsersAction) -> None:
    fuse = subparsers.add_parser(
        "fuse",
        help="give each point of a cloud its temperature from calibrated thermal frames",
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
        help="reconstruct a structured-light capture and fuse thermal frames into a temperature field",
        description="Reconstruct a capture directory (as `thermofield reconstruct`) and fuse the thermal "
                    "frames onto the cloud (as `thermofield fuse`), in one step.",
    )
    field.add_argument("--rig", required=True, type=Path, help="rig file (JSON)")
    field.add_argument("--captures", required=True, type=Path,
                       help="directory with sequence.json and the camera frames")
    field.add_argument("--camera", help="camera device name (default: the rig's only camera)")
    field.add_argument("--projector", help="projector device name (default: the rig's only projector)")
    _add_thermal_arguments(field)
    field.set_defaults(handler=_run_field)


def thermal_views(rig: Rig, frames: list[Path], device_names: list[str] | None,
                  emissivity: float | None) -> list[ThermalView]:
    """Read thermal frames for the named (or the only) thermal devices, one view per device."""
    names = device_names or [None]
    if len(names) not in (1, len(frames)):
        raise InputError(
            f"--thermal-device takes one name or one per frame; got {len(names)} names for {len(frames)} frames"
        )
    if len(names) == 1:
        names = names * len(frames)
    grouped: dict[str, list[np.ndarray]] = {}
    for path, name in zip(frames, names):
        device_name, device = rig.device(name, "thermal")
        grouped.setdefault(device_name, []).append(read_thermal_frame(path, device.size, emissivity))
    return [ThermalView(rig.devices[name], np.stack(images)) for name, images in grouped.items()]


def _measuring_viewpoint(rig: Rig, views: list[ThermalView]) -> np.ndarray:
    """The centre of the rig's only camera (which measured the cloud), else of the first thermal camera."""
    cameras = [device for device in rig.devices.values() if device.kind == "camera"]
    device = cameras[0] if len(cameras) == 1 else views[0].device
    return camera_center(device.R_array, device.t_array)


def _fuse_and_write(rig: Rig, cloud: dict[str, np.ndarray], args: argparse.Namespace, source: str) -> int:
    if args.emissivity is not None and not 0.0 < args.emissivity <= 1.0:
        raise InputError(f"--emissivity must be in (0, 1]; got {args.emissivity}")
    if not 0.0 < args.max_view_angle < 90.0:
        raise InputError(f"--max-view-angle must be in (0, 90) degrees; got {args.max_view_angle}")
    views = thermal_views(rig, args.thermal, args.thermal_device, args.emissivity)
    field = temperature_field(cloud, views, _measuring_viewpoint(rig, views), args.max_view_angle)
    write_cloud(args.out, field, comments=[f"thermofield temperature field of {source}",
                                           "temperature in degrees C (nan: unseen), view_angle in degrees"])
    seen = np.isfinite(field["temperature"])
    summary = (f"{seen.sum()} of {len(seen)} points have a temperature"
               + (f", {np.min(field['temperature'][seen]):.1f} to {np.max(field['temperature'][seen]):.1f} C"
                  if seen.any() else ""))
    print(f"{args.out}: {summary}")
    return 0


def _run_fuse(args: argparse.Namespace) -> int:
    rig = load_rig(args.rig)
    cloud = read_cloud(args.cloud)
    missing = [name for name in ("x", "y", "z") if name not in cloud]
    if missing:
        raise InputError(f"{args.cloud}: the cloud has no {', '.join(missing)} vertex properties")
    return _fuse_and_write(rig, cloud, args, args.cloud.name)


def _run_field(args: argparse.Namespace) -> int:
    rig = load_rig(args.rig)
    cloud = reconstruct_from_files(args.rig, args.captures, args.camera, args.projector)
    return _fuse_and_write(rig, cloud, args, args.captures.name)
