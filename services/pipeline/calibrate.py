"""Use cases: calibrate a camera, a projector, place a device in a rig, and calibrate a station of several heads to
one world frame, from images in memory.

The command line reads the images from directories and writes the results to files; the calibrate
actor passes uploaded or gateway-filmed images. Every check is made here, with errors that name the
image (by the label the caller gives it) and what is wrong.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from matplotlib.figure import Figure

from services.calibration.camera import INTRINSIC_NAMES, calibrate_camera
from services.calibration.corner_window import WindowSelection, select_corner_window
from services.calibration.corners import DEFAULT_WINDOW_FRACTION, BoardDetection, detect_board, refine_corners
from services.calibration.determination import poorly_determined
from services.calibration.frontal import calibrate_with_frontal_refinement
from services.calibration.model_selection import ModelSelection
from services.calibration.projector import calibrate_projector, projector_corners
from services.calibration.report import coverage_map, residual_bars, residual_vectors
from services.calibration.station import POSE_NAMES, BoardObservation, adjust_station, tied_groups
from services.calibration.stereo import calibrate_stereo
from services.errors import InputError
from services.formats.board import MIN_VIEWS, BoardSpec
from services.formats.calibration import (
    CalibratedView, CameraCalibrationFile, CornerWindowRecord, ModelCandidate, ModelSelectionRecord,
    ProjectorCalibrationFile, RejectedView, StationCalibrationFile, StationDeviceRecord, StationOverlapRecord,
    StereoCalibrationFile, WindowCandidate,
)
from services.formats.rig import Head, Rig
from services.formats.sequence import Sequence as PatternSequence
from services.geometry.camera_model import CameraModel, DeviceKind
from services.intensity import percentile_stretch
from services.structured_light.decode import decode

LabelledImage = tuple[str, np.ndarray]
"""An image and the label that names it in errors and reports (its file name)."""


def detect_in_images(images: Sequence[LabelledImage], board: BoardSpec,
                     unreadable: Sequence[str] = ()) -> tuple[list[BoardDetection], tuple[int, int]]:
    """Detect the board in every image; one error lists every image that failed and why, after the
    ``unreadable`` ones (the caller's reasons for the images it could not read)."""
    detections, problems, size = [], list(unreadable), None
    for label, image in images:
        image_size = (image.shape[1], image.shape[0])
        if size is None:
            size = image_size
        elif image_size != size:
            problems.append(f"{label}: image is {image_size[0]}x{image_size[1]} but {images[0][0]} is "
                            f"{size[0]}x{size[1]}; all images must have one size")
            continue
        detection = detect_board(image, board)
        if detection is None:
            problems.append(f"{label}: no {_describe(board)} found (polarity {board.polarity}); "
                            "check the board file or remove the image")
            continue
        detections.append(detection)
    if problems:
        raise InputError(f"{len(problems)} of {len(images) + len(unreadable)} images cannot be used:\n  "
                         + "\n  ".join(problems))
    return detections, size


def capture_board_image(sequence: PatternSequence, frames: np.ndarray) -> np.ndarray:
    """The board image of a structured-light capture: its decoded intensity (white frame, or the mean of the
    phase frames), in the frames' dtype."""
    intensity = decode(frames, sequence, edge_margin=0).intensity
    return np.clip(np.round(intensity), 0, np.iinfo(frames.dtype).max).astype(frames.dtype)


def thermal_board_image(frame: np.ndarray) -> np.ndarray:
    """A filmed thermal frame (degrees C) as a 16-bit board image: its 0.5..99.5 percentile range stretched
    over 0..65535 (:func:`services.intensity.percentile_stretch`), so that corner detection keeps its fine
    levels."""
    return np.round(percentile_stretch(frame, 65535.0)).astype(np.uint16)


def uploaded_board_image(content: bytes, *, suffix: str, source: str, size: tuple[int, int] | None = None
                         ) -> np.ndarray:
    """A board image from an uploaded file: an 8- or 16-bit PNG, BMP or TIFF as it is; a radiometric thermal
    file (:func:`services.formats.thermal.is_radiometric_file`) read as degrees C
    (:func:`services.formats.thermal.decode_thermal_frame`, with the file's own radiometric parameters) and
    stretched by :func:`thermal_board_image`."""
    from services.formats.images import decode_image
    from services.formats.thermal import decode_thermal_frame, is_radiometric_file

    if is_radiometric_file(content, suffix):
        return thermal_board_image(decode_thermal_frame(content, suffix=suffix, source=source, size=size))
    return decode_image(content, source)


def _describe(board: BoardSpec) -> str:
    cols, rows = board.pattern_size
    feature = "circle" if board.type == "circles" else "inner-corner"
    return f"{board.type} of {cols}x{rows} {feature}s"


@dataclass(frozen=True)
class CameraCalibrationOutcome:
    """The calibration file's content and its report figures (``residual_bars``, ``residual_vectors``,
    ``coverage``)."""

    calibration: CameraCalibrationFile
    figures: dict[str, Figure]


def calibrate_camera_views(*, images: Sequence[LabelledImage], board: BoardSpec, name: str,
                           kind: DeviceKind = "camera", distortion: str = "standard",
                           unreadable: Sequence[str] = (), source: str = "the images") -> CameraCalibrationOutcome:
    """Zhang's calibration of one camera from board images, with automatic outlier rejection.

    ``unreadable`` lists the reasons why other images could not be read; they are reported with the
    images in which no board is found.
    """
    if len(images) + len(unreadable) < MIN_VIEWS:
        raise InputError(f"{source}: {len(images) + len(unreadable)} images; calibration needs at least "
                         f"{MIN_VIEWS} views")
    detections, size = detect_in_images(images, board, unreadable)
    object_points = [board.object_points()[d.ids] for d in detections]
    image_points, window = [d.image_points for d in detections], None
    if board.type != "circles":
        window = select_corner_window([image for _, image in images], image_points, object_points, size, distortion)
        result, image_points = calibrate_with_frontal_refinement(
            [image for _, image in images], object_points, window.image_points, size, distortion, board.square_mm,
            window.fraction, flatten=board.type == "chessboard")
    else:
        result = calibrate_camera(object_points, image_points, size, distortion)
    names = [label for label, _ in images]
    views = [
        CalibratedView(image=names[i], rms_px=float(rms), polarity=detections[i].polarity, R=R.tolist(),
                       t=t.tolist(), pose_std=std.tolist())
        for i, rms, R, t, std in zip(result.views, result.per_view_rms, result.rotations, result.translations,
                                     result.pose_std)
    ]
    calibration = CameraCalibrationFile(
        name=name, kind=kind, width=size[0], height=size[1], K=result.K.tolist(), dist=result.dist.tolist(),
        distortion_model=result.distortion_model, rms_px=result.rms, std=result.std, board=board, views=views,
        rejected=[RejectedView(image=names[i], reason=reason) for i, reason in result.rejected],
        model_selection=_model_selection_record(result.model_selection),
        corner_window=_corner_window_record(window), poorly_determined=poorly_determined(result),
    )
    kept_points = [image_points[i] for i in result.views]
    figures = {
        "residual_bars": residual_bars(result.per_view_rms, [names[i] for i in result.views], result.rms),
        "residual_vectors": residual_vectors(kept_points, result.residuals, size),
        "coverage": coverage_map(kept_points, size),
    }
    return CameraCalibrationOutcome(calibration, figures)


def _model_selection_record(selection: ModelSelection | None) -> ModelSelectionRecord | None:
    if selection is None:
        return None
    return ModelSelectionRecord(reason=selection.reason, candidates=[
        ModelCandidate(model=fit.model, rms_px=fit.rms, parameters=fit.parameters, bic=fit.bic)
        for fit in selection.fits])


def _corner_window_record(window: WindowSelection | None) -> CornerWindowRecord | None:
    if window is None:
        return None
    return CornerWindowRecord(fraction=window.fraction, reason=window.reason, candidates=[
        WindowCandidate(fraction=fraction, held_out_rms_px=rms) for fraction, rms in window.held_out_rms.items()])


BoardCapture = tuple[str, PatternSequence, np.ndarray]
"""A structured-light capture of the board in one pose: its label, manifest and frames."""


def calibrate_projector_captures(*, captures: Sequence[BoardCapture], board: BoardSpec,
                                 camera: CameraCalibrationFile, name: str = "projector",
                                 distortion: str = "radial") -> tuple[Rig, ProjectorCalibrationFile]:
    """The projector's intrinsics and pose from board captures coding both axes, by local homographies.

    Returns the rig (the camera at the origin and the projector) and the projector report.
    """
    if len(captures) < MIN_VIEWS:
        raise InputError(f"{len(captures)} captures given; projector calibration needs at least {MIN_VIEWS} "
                         "board poses")
    objects, camera_points, projector_points, problems, projector_size = [], [], [], [], None
    # The camera's corners are refined as its own calibration refined them.
    window_fraction = camera.corner_window.fraction if camera.corner_window else DEFAULT_WINDOW_FRACTION
    for label, sequence, frames in captures:
        size = (sequence.projector.width, sequence.projector.height)
        if projector_size is not None and size != projector_size:
            problems.append(f"{label}: projector is {size[0]}x{size[1]} but {captures[0][0]} has "
                            f"{projector_size[0]}x{projector_size[1]}")
            continue
        projector_size = size
        if (frames.shape[2], frames.shape[1]) != (camera.width, camera.height):
            problems.append(f"{label}: frames are {frames.shape[2]}x{frames.shape[1]} but the camera {camera.name!r} "
                            f"is calibrated for {camera.width}x{camera.height}")
            continue
        # No edge margin: it is for depth outlines, and around each pixel rejected inside the board (a noisy
        # dark square) it would drop 49 good ones; the corners' homographies need the whole window.
        decoded = decode(frames, sequence, edge_margin=0)
        if set(decoded.coded_axes) != {"x", "y"}:
            problems.append(f"{label}: the sequence codes only {'/'.join(decoded.coded_axes)}; both axes are "
                            "needed (thermofield patterns --axes xy)")
            continue
        lit = np.clip(np.round(decoded.intensity), 0, np.iinfo(frames.dtype).max).astype(frames.dtype)
        detection = detect_board(lit, board)
        if detection is None:
            problems.append(f"{label}: no {_describe(board)} found in the lit frame")
            continue
        camera_corners = refine_corners(lit, detection.image_points, window_fraction)
        half_window = max(2, int(0.5 * _corner_spacing(camera_corners)))
        corners, found = projector_corners(camera_corners, decoded.projector_x, decoded.projector_y,
                                           half_window, decoded.modulation)
        if found.sum() < 6:
            problems.append(f"{label}: only {found.sum()} board corners were decoded (is the board lit?)")
            continue
        objects.append(board.object_points()[detection.ids[found]])
        camera_points.append(camera_corners[found])
        projector_points.append(corners[found])
    if problems:
        raise InputError(f"{len(problems)} of {len(captures)} captures cannot be used:\n  " + "\n  ".join(problems))
    result = calibrate_projector(objects, camera_points, projector_points, (np.asarray(camera.K), np.asarray(camera.dist)),
                                 (camera.width, camera.height), projector_size, distortion)
    projector = CameraModel(kind="projector", width=projector_size[0], height=projector_size[1],
                            K=result.projector.K, dist=result.projector.dist, R=result.stereo.R, t=result.stereo.t)
    labels = [label for label, _, _ in captures]
    report = ProjectorCalibrationFile(
        projector_rms_px=result.projector.rms, stereo_rms_px=result.stereo.rms, baseline_mm=result.stereo.baseline_mm,
        std=result.projector.std, views=[labels[i] for i in result.projector.views],
        per_view_rms_px=result.projector.per_view_rms.tolist(),
        stereo_std=dict(zip(("rx", "ry", "rz", "tx", "ty", "tz"), result.stereo.pose_std.tolist())),
        stereo_per_view_rms_px=result.stereo.per_view_rms.tolist(),
        rejected=[RejectedView(image=labels[i], reason=reason) for i, reason in result.projector.rejected],
    )
    return Rig({camera.name: camera.device(), name: projector}), report


def _corner_spacing(points: np.ndarray) -> float:
    distances = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    return float(np.median(distances.min(axis=1)))


def place_device(*, board: BoardSpec, rig: Rig, device: str, reference_images: Sequence[LabelledImage],
                 device_images: Sequence[LabelledImage], camera: str | None = None,
                 intrinsics: CameraModel | None = None,
                 source: str = "the pairs") -> tuple[Rig, StereoCalibrationFile]:
    """Place ``device`` relative to the rig's camera from paired board images (stereo calibration).

    ``reference_images[i]`` (the camera) and ``device_images[i]`` show the same board pose.
    ``intrinsics`` calibrates the device when the rig does not hold it yet. Returns the rig with the
    device placed and the stereo report.
    """
    camera_name, camera_model = rig.device(camera, "camera")
    if intrinsics is None:
        if device not in rig.devices:
            raise InputError(f"intrinsics: the rig has no device {device!r}; give its intrinsics",
                             parameter="intrinsics")
        intrinsics = rig.devices[device]
    if not reference_images or len(reference_images) != len(device_images):
        raise InputError(f"{source}: give the same number of {camera_name} and {device} images, at least one; "
                         f"got {len(reference_images)} and {len(device_images)}")
    reference, reference_size = detect_in_images(reference_images, board)
    seen, device_size = detect_in_images(device_images, board)
    for label, size, expected in ((camera_name, reference_size, camera_model), (device, device_size, intrinsics)):
        if size != expected.size:
            raise InputError(f"{source}: the {label} images are {size[0]}x{size[1]} but the calibration of "
                             f"{label} is for {expected.width}x{expected.height}")
    object_points, first, second, pair_names = [], [], [], []
    for (label, _), a, b in zip(reference_images, reference, seen):
        shared, index_a, index_b = np.intersect1d(a.ids, b.ids, return_indices=True)
        if len(shared) >= 4:
            object_points.append(board.object_points()[shared])
            first.append(a.image_points[index_a])
            second.append(b.image_points[index_b])
            pair_names.append(label)
    result = calibrate_stereo(object_points, first, second, (camera_model.K, camera_model.dist),
                              (intrinsics.K, intrinsics.dist), reference_size)
    placed = intrinsics.replace(R=result.R @ camera_model.R, t=result.R @ camera_model.t + result.t)
    report = StereoCalibrationFile(device=device, reference=camera_name, stereo_rms_px=result.rms,
                                   baseline_mm=result.baseline_mm, pairs=pair_names,
                                   per_view_rms_px=result.per_view_rms.tolist())
    return rig.with_device(device, placed), report


IntrinsicsMode = Literal["fixed", "refined"]


def station_from_heads(heads: Mapping[str, Rig], thermal: Mapping[str, CameraModel] | None = None) -> Rig:
    """A station rig from its heads' own rigs (``calibrate projector``'s, one camera and one projector each) and
    its thermal cameras' intrinsics: devices ``camera-NAME`` and ``projector-NAME`` with each head's
    camera-projector pose kept, every head's camera at the origin (until :func:`calibrate_station` places it)."""
    devices, station_heads = {}, []
    for name, head_rig in heads.items():
        if len(head_rig.heads) != 1:
            raise InputError(f"head {name!r}: its rig must hold one camera and one projector (calibrate projector's "
                             f"output); it has {sorted(head_rig.devices)}")
        head = head_rig.heads[0]
        camera, projector = head_rig.devices[head.camera], head_rig.devices[head.projector]
        relative = projector.R @ camera.R.T
        devices[f"camera-{name}"] = camera.replace(R=np.eye(3), t=np.zeros(3))
        devices[f"projector-{name}"] = projector.replace(R=relative, t=projector.t - relative @ camera.t)
        station_heads.append(Head(name, f"camera-{name}", f"projector-{name}"))
    for name, device in (thermal or {}).items():
        if name in devices:
            raise InputError(f"thermal camera {name!r}: a head's device already has that name")
        devices[name] = device.replace(kind="thermal", R=np.eye(3), t=np.zeros(3))
    return Rig(devices, station_heads=tuple(station_heads))


@dataclass(frozen=True)
class StationCalibrationOutcome:
    """The calibrated station rig (version 2) and the calibration report."""

    rig: Rig
    report: StationCalibrationFile


def calibrate_station(*, board: BoardSpec, rig: Rig, views: Mapping[str, Sequence[LabelledImage]],
                      world: str | None = None, intrinsics: IntrinsicsMode = "refined", jackknife: bool = True,
                      source: str = "the views") -> StationCalibrationOutcome:
    """Place every head (and thermal camera) of a station in one world frame by bundle adjustment.

    ``rig`` is the station: its heads, each camera's intrinsics and each head's camera-projector pose (from the
    heads' own calibrations), and the thermal cameras' intrinsics; the poses of its cameras are recomputed, but the
    device fixing the world frame (``world``: a head or a device; default the first head's camera) keeps its pose
    in ``rig``, so a station re-calibrated keeps its world frame. ``views`` holds, per head name (its camera's
    images) or thermal camera name, labelled board images; one label (the file name) in several cameras' images is
    one board pose seen by all of them. Images where no board is found are listed in the report (``unseen``).
    ``intrinsics="refined"`` refines every camera's focal lengths, principal point and non-zero distortion
    coefficients with the poses; ``"fixed"`` keeps them. A projector follows its head's camera.
    """
    names: list[str] = []  # adjusted devices in order: the heads' cameras, then thermal cameras
    heads_of: dict[str, str] = {}
    for key in views:
        if key not in {h.name for h in rig.heads} and (key not in rig.devices or rig.devices[key].kind != "thermal"):
            raise InputError(f"{source}: {key!r} is neither a head of the station ({[h.name for h in rig.heads]}) "
                             f"nor one of its thermal cameras "
                             f"({sorted(n for n, d in rig.devices.items() if d.kind == 'thermal')})")
    for head in rig.heads:
        if head.name not in views:
            raise InputError(f"{source}: no images of head {head.name!r}; every head must see the board")
        names.append(head.camera)
        heads_of[head.camera] = head.name
    names += sorted(key for key in views if key not in heads_of.values())
    labels = sorted({label for images in views.values() for label, _ in images})
    observations, unseen, problems = [], [], []
    for index, name in enumerate(names):
        key = heads_of.get(name, name)
        device = rig.devices[name]
        for label, image in views[key]:
            if (image.shape[1], image.shape[0]) != device.size:
                problems.append(f"{key}/{label}: image is {image.shape[1]}x{image.shape[0]} but {name} is "
                                f"{device.width}x{device.height}")
                continue
            detection = detect_board(image, board)
            if detection is None:
                unseen.append(f"{key}/{label}: no {_describe(board)} found")
                continue
            observations.append(BoardObservation(index, labels.index(label), board.object_points()[detection.ids],
                                                 detection.image_points))
    if problems:
        raise InputError(f"{source}: {len(problems)} images cannot be used:\n  " + "\n  ".join(problems))
    seen_labels = sorted({o.view for o in observations})
    renumber = {view: i for i, view in enumerate(seen_labels)}
    observations = [BoardObservation(o.camera, renumber[o.view], o.object_points, o.image_points)
                    for o in observations]
    labels = [labels[view] for view in seen_labels]
    blind = [heads_of.get(n, n) for i, n in enumerate(names) if not any(o.camera == i for o in observations)]
    if blind:
        raise InputError(f"{source}: the board was found in no image of {blind}")
    groups = tied_groups(observations, len(names))
    if len(groups) > 1:
        described = "; ".join(", ".join(heads_of.get(names[i], names[i]) for i in sorted(g)) for g in groups)
        raise InputError(f"{source}: the cameras fall into groups that share no board view ({described}); add views "
                         "of the board seen by neighbouring heads at once")
    if world is None:
        world = names[0]
    elif world in {h.name for h in rig.heads}:
        world = rig.head(world).camera
    if world not in names:
        raise InputError(f"world: {world!r} is not a head or an adjusted camera of the station ({names})")
    reference = names.index(world)
    refined = None
    if intrinsics == "refined":
        refined = [INTRINSIC_NAMES[:4] + tuple(INTRINSIC_NAMES[4 + i] for i in np.flatnonzero(rig.devices[n].dist))
                   for n in names]
    try:
        bundle = adjust_station(observations, [(rig.devices[n].K, rig.devices[n].dist) for n in names],
                                reference=reference, reference_pose=(rig.devices[world].R, rig.devices[world].t),
                                refined_intrinsics=refined, jackknife=jackknife)
    except ValueError as error:
        raise InputError(f"{source}: {error}") from None
    devices = dict(rig.devices)
    for index, name in enumerate(names):
        old = rig.devices[name]
        R, t = bundle.rotations[index], bundle.translations[index]
        devices[name] = old.replace(K=bundle.K[index], dist=bundle.dist[index][:old.dist.size], R=R, t=t)
        if name in heads_of:
            projector_name = rig.head(heads_of[name]).projector
            projector = rig.devices[projector_name]
            relative = projector.R @ old.R.T
            devices[projector_name] = projector.replace(R=relative @ R, t=relative @ (t - old.t) + projector.t)
    report = _station_report(board, names, heads_of, world, intrinsics, labels, unseen, observations, bundle)
    return StationCalibrationOutcome(Rig(devices, rig.units, rig.station_heads or rig.heads), report)


def _station_report(board, names, heads_of, world, intrinsics, labels, unseen, observations, bundle
                    ) -> StationCalibrationFile:
    counts = np.array([len(o.object_points) for o in observations])

    def rms(selected: list[int], values: np.ndarray) -> float:
        return float(np.sqrt(np.sum(counts[selected] * values[selected] ** 2) / np.sum(counts[selected])))

    devices = []
    for index, name in enumerate(names):
        mine = [i for i, o in enumerate(observations) if o.camera == index]
        devices.append(StationDeviceRecord(
            device=name, head=heads_of.get(name), views=len(mine), rms_px=rms(mine, bundle.observation_rms_px),
            pose_std=dict(zip(POSE_NAMES, bundle.pose_std[index].tolist())),
            pose_std_jacobian=dict(zip(POSE_NAMES, bundle.pose_std_jacobian[index].tolist())),
            pose_std_jackknife=dict(zip(POSE_NAMES, bundle.pose_std_jackknife[index].tolist()))))
    overlaps = []
    for a in range(len(names)):
        for b in range(a + 1, len(names)):
            shared = ({o.view for o in observations if o.camera == a} & {o.view for o in observations if o.camera == b})
            if shared:
                selected = [i for i, o in enumerate(observations) if o.view in shared and o.camera in (a, b)]
                overlaps.append(StationOverlapRecord(devices=[names[a], names[b]], views=len(shared),
                                                     rms_px=rms(selected, bundle.observation_rms_px),
                                                     rms_mm=rms(selected, bundle.observation_rms_mm)))
    return StationCalibrationFile(world=world, intrinsics=intrinsics, board=board, rms_px=bundle.rms_px,
                                  overlap_rms_px=bundle.overlap_rms_px, overlap_rms_mm=bundle.overlap_rms_mm,
                                  devices=devices, overlaps=overlaps, views=labels, unseen=unseen)
