"""``thermofield calibrate camera|projector|stereo``: calibration from board images to files and a rig."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from services.calibration.camera import MIN_VIEWS, calibrate_camera
from services.calibration.corners import BoardDetection, detect_board
from services.calibration.model_selection import ModelSelection
from services.calibration.projector import calibrate_projector, projector_corners
from services.calibration.report import coverage_map, residual_bars, residual_vectors
from services.calibration.stereo import calibrate_stereo
from services.errors import InputError
from services.formats.board import BoardSpec, load_board
from services.formats.calibration import (
    CalibratedView,
    CameraCalibrationFile,
    ModelCandidate,
    ModelSelectionRecord,
    ProjectorCalibrationFile,
    RejectedView,
    StereoCalibrationFile,
    load_camera_calibration,
    save_camera_calibration,
    save_figure,
    save_projector_calibration,
    save_stereo_calibration,
)
from services.formats.images import FRAME_SUFFIXES, read_frame
from services.formats.rig import Device, Rig, load_rig, save_rig
from services.formats.sequence import read_capture
from services.structured_light.decode import decode

REPORT_FIGURES = ("residual_bars", "residual_vectors", "coverage")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("calibrate", help="calibrate cameras, the projector and the infrared camera")
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


def list_frames(directory: Path) -> list[Path]:
    """Frame files of a directory in name order; an error names the directory if there are none."""
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory")
    frames = sorted(p for p in directory.iterdir() if p.suffix.lower() in FRAME_SUFFIXES + (".jpg", ".jpeg"))
    if not frames:
        raise InputError(f"{directory}: no image files ({', '.join(FRAME_SUFFIXES + ('.jpg',))})")
    return frames


def detect_in_frames(paths: list[Path], board: BoardSpec, read=read_frame) -> tuple[list[BoardDetection], tuple[int, int]]:
    """Detect the board in every frame (``read(path)`` gives its image); one error lists every frame that
    failed and why."""
    detections, problems, size = [], [], None
    for path in paths:
        try:
            image = read(path)
        except InputError as error:
            problems.append(str(error))
            continue
        frame_size = (image.shape[1], image.shape[0])
        if size is None:
            size = frame_size
        elif frame_size != size:
            problems.append(f"{path}: image is {frame_size[0]}x{frame_size[1]} but {paths[0].name} is "
                            f"{size[0]}x{size[1]}; all images must have one size")
            continue
        detection = detect_board(image, board)
        if detection is None:
            problems.append(f"{path}: no {_describe(board)} found (polarity {board.polarity}); "
                            "check the board file or remove the image")
            continue
        detections.append(detection)
    if problems:
        raise InputError(f"{len(problems)} of {len(paths)} images cannot be used:\n  " + "\n  ".join(problems))
    return detections, size


def _describe(board: BoardSpec) -> str:
    cols, rows = board.pattern_size
    feature = "circle" if board.type == "circles" else "inner-corner"
    return f"{board.type} of {cols}x{rows} {feature}s"


def capture_board_image(directory: Path, manifest: Path | None = None) -> np.ndarray:
    """The board image of a structured-light capture: its decoded intensity (white frame, or the mean of the
    phase frames), in the frames' dtype."""
    sequence, frames = read_capture(directory, manifest)
    intensity = decode(frames, sequence, edge_margin=0).intensity
    return np.clip(np.round(intensity), 0, np.iinfo(frames.dtype).max).astype(frames.dtype)


def run_camera(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    if args.captures is not None:
        paths, names = list(args.captures), [str(directory) for directory in args.captures]
        read = lambda directory: capture_board_image(directory, args.manifest)  # noqa: E731
        source = f"{len(paths)} captures"
    else:
        paths = list_frames(args.images)
        names, read, source = [p.name for p in paths], read_frame, f"{args.images}: {len(paths)} images"
    if len(paths) < MIN_VIEWS:
        raise InputError(f"{source}; calibration needs at least {MIN_VIEWS} views")
    detections, size = detect_in_frames(paths, board, read)
    object_points = [board.object_points()[d.ids] for d in detections]
    result = calibrate_camera(object_points, [d.image_points for d in detections], size, args.distortion)
    views = [
        CalibratedView(image=names[i], rms_px=float(rms), polarity=detections[i].polarity, R=R.tolist(),
                       t=t.tolist(), pose_std=std.tolist())
        for i, rms, R, t, std in zip(result.views, result.per_view_rms, result.rotations, result.translations,
                                     result.pose_std)
    ]
    output = CameraCalibrationFile(
        name=args.name or args.kind, kind=args.kind, width=size[0], height=size[1], K=result.K.tolist(),
        dist=result.dist.tolist(), distortion_model=result.distortion_model, rms_px=result.rms, std=result.std,
        board=board, views=views,
        rejected=[RejectedView(image=names[i], reason=reason) for i, reason in result.rejected],
        model_selection=_model_selection_record(result.model_selection),
    )
    kept_points = [detections[i].image_points for i in result.views]
    figures = {
        "residual_bars": residual_bars(result.per_view_rms, [names[i] for i in result.views], result.rms),
        "residual_vectors": residual_vectors(kept_points, result.residuals, size),
        "coverage": coverage_map(kept_points, size),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name, figure in figures.items():
        save_figure(figure, report_path(args.out, name))
    save_camera_calibration(output, args.out)
    print(f"{output.name}: RMS {result.rms:.3f} px over {len(result.views)} views "
          f"({len(result.rejected)} rejected); fx {result.K[0, 0]:.2f} +- {result.std['fx']:.2f}, "
          f"fy {result.K[1, 1]:.2f} +- {result.std['fy']:.2f}, cx {result.K[0, 2]:.2f}, cy {result.K[1, 2]:.2f}")
    if result.model_selection is not None:
        print(f"{output.name}: lens model {result.distortion_model}: {result.model_selection.reason}")
    return 0


def _model_selection_record(selection: ModelSelection | None) -> ModelSelectionRecord | None:
    if selection is None:
        return None
    return ModelSelectionRecord(reason=selection.reason, candidates=[
        ModelCandidate(model=fit.model, rms_px=fit.rms, parameters=fit.parameters, bic=fit.bic)
        for fit in selection.fits])


def report_path(calibration_path: Path, figure: str) -> Path:
    """Where the report figure ``figure`` of a calibration file goes: beside it, sharing its stem."""
    return calibration_path.with_name(f"{calibration_path.stem}_{figure}.png")


def run_projector(args: argparse.Namespace) -> int:
    board = load_board(args.board)
    camera = load_camera_calibration(args.camera)
    if len(args.captures) < MIN_VIEWS:
        raise InputError(f"{len(args.captures)} captures given; projector calibration needs at least {MIN_VIEWS} "
                         "board poses")
    objects, camera_points, projector_points, problems, projector_size = [], [], [], [], None
    for directory in args.captures:
        sequence, frames = read_capture(directory, args.manifest)
        size = (sequence.projector.width, sequence.projector.height)
        if projector_size is not None and size != projector_size:
            problems.append(f"{directory}: projector is {size[0]}x{size[1]} but {args.captures[0]} has "
                            f"{projector_size[0]}x{projector_size[1]}")
            continue
        projector_size = size
        if (frames.shape[2], frames.shape[1]) != (camera.width, camera.height):
            problems.append(f"{directory}: frames are {frames.shape[2]}x{frames.shape[1]} but {args.camera} is "
                            f"for {camera.width}x{camera.height}")
            continue
        # No EDGE margin: it is for depth outlines, and around each pixel rejected inside the board (a noisy
        # dark square) it would drop 49 good ones; the corners' homographies need the whole window.
        decoded = decode(frames, sequence, edge_margin=0)
        if set(decoded.coded_axes) != {"x", "y"}:
            problems.append(f"{directory}: the sequence codes only {'/'.join(decoded.coded_axes)}; both axes are "
                            "needed (thermofield patterns --axes xy)")
            continue
        lit = np.clip(np.round(decoded.intensity), 0, np.iinfo(frames.dtype).max).astype(frames.dtype)
        detection = detect_board(lit, board)
        if detection is None:
            problems.append(f"{directory}: no {_describe(board)} found in the lit frame")
            continue
        half_window = max(2, int(0.5 * _corner_spacing(detection.image_points)))
        corners, found = projector_corners(detection.image_points, decoded.projector_x, decoded.projector_y,
                                           half_window, decoded.modulation)
        if found.sum() < 6:
            problems.append(f"{directory}: only {found.sum()} board corners were decoded (is the board lit?)")
            continue
        objects.append(board.object_points()[detection.ids[found]])
        camera_points.append(detection.image_points[found])
        projector_points.append(corners[found])
    if problems:
        raise InputError(f"{len(problems)} of {len(args.captures)} captures cannot be used:\n  " + "\n  ".join(problems))
    result = calibrate_projector(objects, camera_points, projector_points, (np.asarray(camera.K), np.asarray(camera.dist)),
                                 (camera.width, camera.height), projector_size, args.distortion)
    projector = Device(kind="projector", width=projector_size[0], height=projector_size[1],
                       K=result.projector.K.tolist(), dist=result.projector.dist.tolist(),
                       R=result.stereo.R.tolist(), t=result.stereo.t.tolist())
    names = [str(directory) for directory in args.captures]
    report = ProjectorCalibrationFile(
        projector_rms_px=result.projector.rms, stereo_rms_px=result.stereo.rms, baseline_mm=result.stereo.baseline_mm,
        std=result.projector.std, views=[names[i] for i in result.projector.views],
        per_view_rms_px=result.projector.per_view_rms.tolist(),
        stereo_std=dict(zip(("rx", "ry", "rz", "tx", "ty", "tz"), result.stereo.pose_std.tolist())),
        stereo_per_view_rms_px=result.stereo.per_view_rms.tolist(),
        rejected=[RejectedView(image=names[i], reason=reason) for i, reason in result.projector.rejected],
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_projector_calibration(report, projector_report_path(args.out))
    save_rig(Rig(devices={camera.name: camera.device(), args.name: projector}), args.out)
    print(f"{args.name}: projector RMS {result.projector.rms:.3f} px, stereo RMS {result.stereo.rms:.3f} px over "
          f"{len(result.projector.views)} poses; baseline {result.stereo.baseline_mm:.2f} mm")
    return 0


def projector_report_path(rig_path: Path) -> Path:
    """Where ``calibrate projector`` writes its report: beside the rig, sharing its stem."""
    return rig_path.with_name(f"{rig_path.stem}_projector.json")


def _corner_spacing(points: np.ndarray) -> float:
    distances = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    return float(np.median(distances.min(axis=1)))


def run_stereo(args: argparse.Namespace) -> int:
    report = place_device(args.board, args.rig, args.pairs, args.device, args.out, camera_name=args.camera,
                          intrinsics=args.intrinsics)
    print(f"{report.device}: stereo RMS {report.stereo_rms_px:.3f} px over {len(report.pairs)} pairs; "
          f"baseline {report.baseline_mm:.2f} mm from {report.reference}")
    return 0


def place_device(board_path: Path, rig_path: Path, pairs: Path, device_name: str, out: Path, *,
                 camera_name: str | None = None, intrinsics: Path | None = None) -> StereoCalibrationFile:
    """Place ``device_name`` relative to the rig's camera from paired board images (``pairs/<camera>/``,
    ``pairs/<device>/``, paired by file name); write the new rig to ``out`` and the stereo report beside it.

    Every error is an ``InputError`` naming the image or file at fault.
    """
    board = load_board(board_path)
    rig = load_rig(rig_path)
    camera_name, camera = rig.device(camera_name, "camera")
    device = _device_to_place(rig, rig_path, device_name, intrinsics)
    reference_dir, device_dir = pairs / camera_name, pairs / device_name
    reference_paths = list_frames(reference_dir)
    device_names = {p.name for p in list_frames(device_dir)}
    paired = [p for p in reference_paths if p.name in device_names]
    if not paired:
        raise InputError(f"{pairs}: no file name appears in both {camera_name}/ and {device_name}/")
    reference, reference_size = detect_in_frames(paired, board)
    seen, device_size = detect_in_frames([device_dir / p.name for p in paired], board)
    for label, size, expected in ((camera_name, reference_size, camera), (device_name, device_size, device)):
        if size != expected.size:
            raise InputError(f"{pairs / label}: images are {size[0]}x{size[1]} but the calibration of "
                             f"{label} is for {expected.width}x{expected.height}")
    object_points, first, second, pair_names = [], [], [], []
    for path, a, b in zip(paired, reference, seen):
        shared, index_a, index_b = np.intersect1d(a.ids, b.ids, return_indices=True)
        if len(shared) >= 4:
            object_points.append(board.object_points()[shared])
            first.append(a.image_points[index_a])
            second.append(b.image_points[index_b])
            pair_names.append(path.name)
    result = calibrate_stereo(object_points, first, second, (camera.K_array, camera.dist_array),
                              (device.K_array, device.dist_array), reference_size)
    R = result.R @ camera.R_array
    t = result.R @ camera.t_array + result.t
    placed = device.model_copy(update={"R": R.tolist(), "t": t.tolist()})
    report = StereoCalibrationFile(device=device_name, reference=camera_name, stereo_rms_px=result.rms,
                                   baseline_mm=result.baseline_mm, pairs=pair_names,
                                   per_view_rms_px=result.per_view_rms.tolist())
    out.parent.mkdir(parents=True, exist_ok=True)
    save_stereo_calibration(report, stereo_report_path(out, device_name))
    save_rig(Rig(units=rig.units, devices={**rig.devices, device_name: placed}), out)
    return report


def stereo_report_path(rig_out: Path, device_name: str) -> Path:
    """Where ``place_device`` writes its stereo report: ``RIG_stereo_DEVICE.json`` beside the rig."""
    return rig_out.with_name(f"{rig_out.stem}_stereo_{device_name}.json")


def _device_to_place(rig: Rig, rig_path: Path, device_name: str, intrinsics: Path | None) -> Device:
    if intrinsics is not None:
        return load_camera_calibration(intrinsics).device()
    if device_name not in rig.devices:
        raise InputError(f"{rig_path}: has no device {device_name!r}; pass its calibration with --intrinsics")
    return rig.devices[device_name]
