"""``thermofield calibrate camera|projector|stereo|station``: calibration from board images to files and a rig."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.errors import InputError
from services.formats.board import load_board
from services.formats.calibration import (
    load_camera_calibration,
    save_camera_calibration,
    save_figure,
    save_projector_calibration,
    save_station_calibration,
    save_stereo_calibration,
)
from services.formats.images import FRAME_SUFFIXES, read_frame
from services.formats.rig import load_rig, save_rig
from services.formats.sequence import read_capture
from services.structured_light.decode import decode
from services.pipeline.calibrate import (
    LabelledImage, calibrate_camera_views, calibrate_projector_captures, calibrate_station, capture_board_image,
    place_device, station_from_heads,
)

REPORT_FIGURES = ("residual_bars", "residual_vectors", "coverage")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("calibrate")
    topics = parser.add_subparsers(dest="calibrate_command", required=True, metavar="TARGET")

    camera = topics.add_parser("camera", help="intrinsics of one camera from board images (Zhang's method)")
    camera.add_argument("--board", required=True, type=Path, help="board specification JSON")
    source = camera.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", type=Path, help="directory of board images")
    source.add_argument("--captures", type=Path, nargs="+",
                        help="structured-light capture directories, one per board pose: the board is found in each "
                             "capture's decoded intensity (the mean of its phase frames, or its white frame)")
    camera.add_argument("--manifest", type=Path, default=None,
                        help="with --captures: the sequence manifest of every capture (default: each DIR/sequence.json)")
    camera.add_argument("--out", required=True, type=Path, help="calibration JSON to write (report PNGs beside it)")
    camera.add_argument("--name", default=None, help="device name (default: the --kind)")
    camera.add_argument("--kind", choices=("camera", "thermal"), default="camera")
    camera.add_argument("--distortion", choices=("none", "radial", "standard", "rational", "auto"), default="standard",
                        help="lens model: none, k1 k2, k1 k2 p1 p2 k3 (default), rational (8 terms), or auto "
                             "(the one the data support best, by the Bayesian information criterion)")
    camera.set_defaults(handler=run_camera)

    projector = topics.add_parser("projector", help="projector intrinsics and pose from structured-light board captures")
    projector.add_argument("--board", required=True, type=Path)
    projector.add_argument("--captures", required=True, type=Path, nargs="+",
                           help="capture directories (sequence.json + frames, both axes coded), one per board pose")
    projector.add_argument("--manifest", type=Path, default=None,
                           help="the sequence manifest of every capture (default: each DIR/sequence.json)")
    projector.add_argument("--camera", required=True, type=Path, help="the camera's calibration JSON")
    projector.add_argument("--out", required=True, type=Path,
                           help="rig JSON to write (camera at the origin); the projector report goes beside it")
    projector.add_argument("--name", default="projector", help="projector name in the rig")
    projector.add_argument("--distortion", choices=("none", "radial", "standard"), default="radial",
                           help="projector lens model (default k1 k2)")
    projector.set_defaults(handler=run_projector)

    stereo = topics.add_parser("stereo", help="pose of a device relative to the rig's camera from paired views")
    stereo.add_argument("--board", required=True, type=Path)
    stereo.add_argument("--pairs", required=True, type=Path,
                        help="directory with one sub-directory per device (named as in the rig), "
                             "frames paired by file name")
    stereo.add_argument("--rig", required=True, type=Path, help="rig holding the reference camera")
    stereo.add_argument("--device", required=True, help="name of the device to place (e.g. thermal)")
    stereo.add_argument("--intrinsics", type=Path, default=None,
                        help="the device's calibration JSON, when the rig does not hold it yet")
    stereo.add_argument("--camera", default=None, help="reference camera name (default: the rig's only camera)")
    stereo.add_argument("--out", required=True, type=Path, help="rig JSON to write (may be --rig)")
    stereo.set_defaults(handler=run_stereo)

    station = topics.add_parser("station", help="every head (and thermal camera) of a station in one world frame, "
                                                "by bundle adjustment over board views neighbouring heads share")
    station.add_argument("--board", required=True, type=Path)
    station.add_argument("--views", required=True, type=Path,
                         help="directory with one sub-directory per head (named as the head) and per thermal camera "
                              "(named as the device); one file name in several sub-directories is one board pose "
                              "seen by those cameras at once")
    heads = station.add_mutually_exclusive_group(required=True)
    heads.add_argument("--rig", type=Path, help="the station's rig (version 2) to calibrate again: its heads, "
                                                "intrinsics and camera-projector poses")
    heads.add_argument("--head", action="append", metavar="NAME=RIG", type=_named_path,
                       help="a head and its own rig (calibrate projector's output), repeatable, in order around the "
                            "part")
    station.add_argument("--thermal", action="append", default=[], metavar="NAME=CAMERA", type=_named_path,
                         help="a thermal camera of the station and its calibration (calibrate camera --kind "
                              "thermal), repeatable")
    station.add_argument("--world", default=None,
                         help="the head or device that fixes the world frame, keeping its pose in the rig "
                              "(default: the first head's camera)")
    station.add_argument("--intrinsics", choices=("refined", "fixed"), default="refined",
                         help="refine every camera's intrinsics with the poses (default), or keep them")
    station.add_argument("--out", required=True, type=Path,
                         help="station rig JSON to write (version 2); the report goes beside it as RIG_station.json")
    station.set_defaults(handler=run_station)


def _named_path(text: str) -> tuple[str, Path]:
    name, separator, path = text.partition("=")
    if not separator or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=FILE; got {text!r}")
    return name, Path(path)


def list_frames(directory: Path) -> list[Path]:
    """Frame files of a directory in name order; an error names the directory if there are none."""
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory")
    frames = sorted(p for p in directory.iterdir() if p.suffix.lower() in FRAME_SUFFIXES + (".jpg", ".jpeg"))
    if not frames:
        raise InputError(f"{directory}: no image files ({', '.join(FRAME_SUFFIXES + ('.jpg',))})")
    return frames


def read_images(paths: list[Path], read=read_frame, label=lambda path: path.name) -> tuple[list[LabelledImage], list[str]]:
    """The images that can be read (``read(path)``), labelled (``label(path)``), and why the others cannot."""
    images, unreadable = [], []
    for path in paths:
        try:
            images.append((label(path), read(path)))
        except InputError as error:
            unreadable.append(str(error))
    return images, unreadable


def _read_all(paths: list[Path]) -> list[LabelledImage]:
    images, unreadable = read_images(paths)
    if unreadable:
        raise InputError(f"{len(unreadable)} of {len(paths)} images cannot be used:\n  " + "\n  ".join(unreadable))
    return images


def capture_board_image(directory: Path, manifest: Path | None = None) -> np.ndarray:
    """The board image of a structured-light capture: its decoded intensity (white frame, or the mean of the
    phase frames), in the frames' dtype."""
    sequence, frames = read_capture(directory, manifest)
    intensity = decode(frames, sequence, edge_margin=0).intensity
    return np.clip(np.round(intensity), 0, np.iinfo(frames.dtype).max).astype(frames.dtype)


def run_camera(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    if args.captures is not None:
        images, unreadable = read_images(
            list(args.captures), lambda directory: capture_board_image(directory, args.manifest), str)
        source = f"{len(args.captures)} captures"
    else:
        images, unreadable = read_images(list_frames(args.images))
        source = str(args.images)
    outcome = calibrate_camera_views(images=images, board=board, name=args.name or args.kind, kind=args.kind,
                                     distortion=args.distortion, unreadable=unreadable, source=source)
    output = outcome.calibration
    for name, figure in outcome.figures.items():
        save_figure(figure, report_path(args.out, name))
    save_camera_calibration(output, args.out)
    print(f"{output.name}: RMS {output.rms_px:.3f} px over {len(output.views)} views "
          f"({len(output.rejected)} rejected); fx {output.K[0][0]:.2f} +- {output.std['fx']:.2f}, "
          f"fy {output.K[1][1]:.2f} +- {output.std['fy']:.2f}, cx {output.K[0][2]:.2f}, cy {output.K[1][2]:.2f}")
    if output.model_selection is not None:
        print(f"{output.name}: lens model {output.distortion_model}: {output.model_selection.reason}")
    for message in output.poorly_determined:
        print(f"{output.name}: {message}")
    return 0


def report_path(calibration_path: Path, figure: str) -> Path:
    """Where the report figure ``figure`` of a calibration file goes: beside it, sharing its stem."""
    return calibration_path.with_name(f"{calibration_path.stem}_{figure}.png")


def run_projector(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    camera = load_camera_calibration(args.camera)
    if len(args.captures) < 3:  # before reading them: frames of a few captures are large
        raise InputError(f"calibrate projector needs at least 3 captures (board poses); got {len(args.captures)}.")
    captures = [(str(directory), *read_capture(directory, args.manifest)) for directory in args.captures]
    rig, report = calibrate_projector_captures(captures=captures, board=board, camera=camera, name=args.name,
                                               distortion=args.distortion)
    save_projector_calibration(report, projector_report_path(args.out))
    save_rig(rig, args.out)
    print(f"{args.name}: projector RMS {report.projector_rms_px:.3f} px, stereo RMS {report.stereo_rms_px:.3f} px "
          f"over {len(report.views)} poses; baseline {report.baseline_mm:.2f} mm")
    return 0


def projector_report_path(rig_path: Path) -> Path:
    """Where ``calibrate projector`` writes its report: beside the rig, sharing its stem."""
    return rig_path.with_name(f"{rig_path.stem}_projector.json")


def run_stereo(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    rig = load_rig(args.rig)
    camera_name, _ = rig.device(args.camera, "camera")
    intrinsics = None
    if args.intrinsics is not None:
        intrinsics = load_camera_calibration(args.intrinsics).device()
    elif args.device not in rig.devices:
        raise InputError(f"{args.rig}: has no device {args.device!r}; pass its calibration with --intrinsics")
    reference_dir, device_dir = args.pairs / camera_name, args.pairs / args.device
    reference_paths = list_frames(reference_dir)
    device_names = {p.name for p in list_frames(device_dir)}
    paired = [p for p in reference_paths if p.name in device_names]
    if not paired:
        raise InputError(f"{args.pairs}: no file name appears in both {camera_name}/ and {args.device}/")
    reference = _read_all(paired)
    device = _read_all([device_dir / p.name for p in paired])
    placed, report = place_device(board=board, rig=rig, device=args.device, reference_images=reference,
                                  device_images=device, camera=camera_name, intrinsics=intrinsics,
                                  source=str(args.pairs))
    save_stereo_calibration(report, stereo_report_path(args.out, args.device))
    save_rig(placed, args.out)
    print(f"{report.device}: stereo RMS {report.stereo_rms_px:.3f} px over {len(report.pairs)} pairs; "
          f"baseline {report.baseline_mm:.2f} mm from {report.reference}")
    return 0


def stereo_report_path(rig_out: Path, device_name: str) -> Path:
    """Where ``calibrate stereo`` writes its stereo report: ``RIG_stereo_DEVICE.json`` beside the rig."""
    return rig_out.with_name(f"{rig_out.stem}_stereo_{device_name}.json")


def run_station(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    thermal = {name: load_camera_calibration(path).device() for name, path in args.thermal}
    if args.rig is not None:
        rig = load_rig(args.rig)
        if not rig.station_heads:
            raise InputError(f"{args.rig}: not a station rig (version 2 with heads); give each head with --head")
        for name, device in thermal.items():
            rig = rig.with_device(name, device.replace(kind="thermal"))
    else:
        rig = station_from_heads({name: load_rig(path) for name, path in args.head}, thermal)
    if not args.views.is_dir():
        raise InputError(f"{args.views}: not a directory")
    views = {directory.name: _read_all(list_frames(directory))
             for directory in sorted(args.views.iterdir()) if directory.is_dir()}
    outcome = calibrate_station(board=board, rig=rig, views=views, world=args.world, intrinsics=args.intrinsics,
                                source=str(args.views))
    report = outcome.report
    save_station_calibration(report, station_report_path(args.out))
    save_rig(outcome.rig, args.out)
    print(f"station: RMS {report.rms_px:.3f} px over {len(report.views)} board views; overlaps RMS "
          f"{report.overlap_rms_px:.3f} px, {report.overlap_rms_mm:.4f} mm on the board; world: {report.world}")
    for record in report.devices:
        sigma = record.pose_std
        print(f"{record.device}: {record.views} views, RMS {record.rms_px:.3f} px; pose sigma "
              f"{max(sigma['rx'], sigma['ry'], sigma['rz']):.4f} deg, {max(sigma['x'], sigma['y'], sigma['z']):.3f} mm")
    for message in report.unseen:
        print(f"not used: {message}")
    return 0


def station_report_path(rig_out: Path) -> Path:
    """Where ``calibrate station`` writes its report: ``RIG_station.json`` beside the rig."""
    return rig_out.with_name(f"{rig_out.stem}_station.json")
