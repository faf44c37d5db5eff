"""Dramatiq actors: plain functions that load their job's inputs, call ``services.pipeline`` and store the outputs.

Each actor takes a job id; its parameters are the job row's ``params`` and its
return value becomes the job's ``result`` (via the JobBookkeeping middleware):
``{"artifacts": {name: digest}, ...}``. Retries and time limits are set per actor:
device and network trouble is retried, bad input (``ValueError``, including
``InputError``) and a full artifact store (``StorageFull``) are not.

- ``scan``: capture with the gateway, reconstruct, fuse, inspect (with a part type), store, stream, summarise.
- ``reconstruct``, ``fuse``, ``register``: one step again on a stored scan, e.g. with
  another calibration set (reconstruct then fuse its cloud) or to check the thermal
  camera's alignment by mutual information (register).
- ``calibrate``: a new calibration set with a device re-placed from paired board images, uploaded or
  filmed by the gateway (a calibration capture job).
- ``calibrate_station``: a new calibration set with every head of a station placed in one world frame from
  uploaded board views (``thermofield calibrate station``).
"""

from __future__ import annotations

import json
import logging
from typing import Any

import dramatiq
import numpy as np
from sqlalchemy import select

from device_gateway.client import GatewayClient, GatewayError
from services.db.calibrations import activate_calibration
from services.db.models import CalibrationSet, Job, PartType, Scan
from services.formats.board import parse_board
from services.formats.images import png_bytes
from services.formats.ply import cloud_from_ply, cloud_to_ply
from services.formats.registration import registration_json
from services.formats.rig import Rig, rig_to_json
from services.formats.sequence import Sequence, parse_sequence
from services.formats.stored_scan import CLOUD, EXPOSURE, FIELD, FRAMES, SEQUENCE, THERMAL, exposure_from_bytes
from services.pipeline.calibrate import calibrate_station as calibrate_station_views
from services.pipeline.calibrate import place_device, thermal_board_image, uploaded_board_image
from services.pipeline.field import fuse_field
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.register import register_scan
from services.pipeline.scan import StageClock, scan_capture, scan_result
from services.pipeline.summary import field_summary, glow_summary
from services.pipeline.warmup import warm_up
from services.runtime import Runtime, current_runtime
from services.simulation.presets import forging_rig
from services.storage.artifacts import ArtifactStore, StorageFull
from services.structured_light.patterns import generate_sequence

logger = logging.getLogger(__name__)
_NOT_RETRIED = (ValueError, StorageFull)  # bad input; a full artifact disk (retrying at once cannot help)


def _options(max_retries: int, time_limit_s: float) -> dict[str, Any]:
    return {"max_retries": max_retries, "time_limit": int(time_limit_s * 1000),
            "min_backoff": 500, "max_backoff": 10_000, "throws": _NOT_RETRIED}


@dramatiq.actor(actor_name="scan", **_options(max_retries=2, time_limit_s=120))
def scan(job_id: str) -> dict[str, Any]:
    """Capture with the gateway, reconstruct, fuse, inspect against the scan's part type (if any), store the
    artifacts, stream to Rerun, summarise.

    The result holds the artifact digests, the seconds each stage took and, when inspected, the verdict and
    the features (``NotDecidable``, none and ``inspection_error`` when the part was not found in the field).
    """
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    part = _part_type(runtime, params["part_type_id"]) if params.get("part_type_id") else None
    clock = StageClock(lambda stage, fraction: runtime.tracker.progress(job_id, stage, fraction))
    clock.start("capture", 0.05)
    try:
        with GatewayClient(runtime.settings.gateway_url) as gateway:
            capture = gateway.capture(thermal_frames=1, exposure=runtime.settings.camera_exposure_mode)
    except GatewayError as error:  # the job's error says which stage lost the devices
        raise GatewayError(f"capture failed: {error}", error.status) from None
    captured_at = float(capture.frame_timestamps[0]) if len(capture.frame_timestamps) else None
    stored = scan_capture(scan_id=params["scan_id"], frames=capture.frames, sequence=capture.sequence,
                          thermal=capture.thermal, rig=rig, tables=runtime.tables, store=runtime.store,
                          exposure=capture.exposure, captured_at=captured_at, part=part, clock=clock,
                          publish=runtime.station_view().publish)
    # the job tracker writes the artifacts, the summary and the verdict onto the scan when it records the result
    return scan_result(scan_id=params["scan_id"], stored=stored, part_type_id=params.get("part_type_id"),
                       stage_seconds=clock.seconds)


@dramatiq.actor(actor_name="reconstruct", **_options(max_retries=1, time_limit_s=120))
def reconstruct(job_id: str) -> dict[str, Any]:
    """The point cloud of a stored scan's frames, with the job's calibration set."""
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    runtime.tracker.progress(job_id, "reconstruct", 0.1)
    exposure = exposure_from_bytes(runtime.store.read_bytes(artifacts[EXPOSURE.name])
                                   if EXPOSURE.name in artifacts else None)
    reconstruction = reconstruct_capture(frames=_load_npy(runtime.store, artifacts[FRAMES.name]),
                                         sequence=_load_sequence(runtime.store, artifacts[SEQUENCE.name]), rig=rig,
                                         tables=runtime.tables, saturation_level=exposure.saturation_level,
                                         source=f"scan {params['scan_id']}")
    cloud = reconstruction.cloud
    glow = glow_summary(reconstruction.glow, exposure)
    return {"artifacts": {CLOUD.name: runtime.store.put_bytes(cloud_to_ply(cloud))}, "point_count": len(cloud),
            "glow": None if glow is None else glow.model_dump(mode="json")}


@dramatiq.actor(actor_name="fuse", **_options(max_retries=1, time_limit_s=120))
def fuse(job_id: str) -> dict[str, Any]:
    """The temperature field of a stored cloud (the scan's, or a reconstruct job's) and the scan's thermal frames."""
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    runtime.tracker.progress(job_id, "fuse", 0.1)
    digest = params.get("cloud_sha256") or artifacts[CLOUD.name]
    cloud = cloud_from_ply(runtime.store.read_bytes(digest), f"artifact {digest}")
    field = fuse_field(cloud=cloud, rig=rig, thermal=[(None, _load_npy(runtime.store, artifacts[THERMAL.name]))],
                       source=f"artifact {digest}")
    return {"artifacts": {FIELD.name: runtime.store.put_bytes(cloud_to_ply(field))},
            "summary": field_summary(field).model_dump(mode="json")}


@dramatiq.actor(actor_name="register", **_options(max_retries=1, time_limit_s=300))
def register(job_id: str) -> dict[str, Any]:
    """Mutual-information registration of a stored scan's thermal frame onto its white camera frame."""
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    runtime.tracker.progress(job_id, "register", 0.1)
    registration, overlay = register_scan(frames=_load_npy(runtime.store, artifacts[FRAMES.name]),
                                          sequence=_load_sequence(runtime.store, artifacts[SEQUENCE.name]),
                                          thermal=_load_npy(runtime.store, artifacts[THERMAL.name]),
                                          model=params["model"])
    return {"artifacts": {"registration.json": runtime.store.put_bytes(registration_json(registration).encode()),
                          "overlay.png": runtime.store.put_bytes(png_bytes(overlay))},
            "nmi": registration.nmi}


@dramatiq.actor(actor_name="calibrate", **_options(max_retries=0, time_limit_s=600))
def calibrate(job_id: str) -> dict[str, Any]:
    """Place a device (e.g. the thermal camera) relative to the camera from paired board images.

    The pairs are the job's uploaded images, or, for a calibration capture job (``params["capture"]``),
    board views the gateway films first. Runs the stereo calibration of ``thermofield calibrate stereo``
    starting from the job's calibration set, and stores the result as a new calibration set.
    """
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    board_json = runtime.store.read_bytes(params["board"])
    board = parse_board(board_json.decode(), f"artifact {params['board']}")
    if "capture" in params:
        runtime.tracker.progress(job_id, "capture", 0.05)
        with GatewayClient(runtime.settings.gateway_url, timeout_s=600) as gateway:
            views = gateway.board_views(json.loads(board_json), params["capture"]["views"],
                                        params["capture"]["interval_s"])
        reference = [(f"camera view {i}", frame) for i, frame in enumerate(views.camera)]
        device = [(f"{params['device']} view {i}", thermal_board_image(frame)) for i, frame in enumerate(views.thermal)]
    else:
        reference = _uploaded_images(runtime.store, params["reference_images"], "reference image")
        device = _uploaded_images(runtime.store, params["device_images"], f"{params['device']} image")
    runtime.tracker.progress(job_id, "calibrate", 0.5)
    calibrated, report = place_device(board=board, rig=rig, device=params["device"], reference_images=reference,
                                      device_images=device, source=f"job {job_id}")
    rig_digest = runtime.store.put_bytes(rig_to_json(calibrated).encode())
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name=params["name"], station=params["station"], rig_sha256=rig_digest,
                                     source="calibration")
        session.add(calibration)
        session.flush()
        if params["activate"]:
            activate_calibration(session, calibration)
        calibration_id = calibration.id
    report_json = report.model_dump_json(indent=2).encode()
    return {"calibration_set_id": calibration_id,
            "artifacts": {"rig.json": rig_digest, "stereo.json": runtime.store.put_bytes(report_json)}}


@dramatiq.actor(actor_name="calibrate_station", **_options(max_retries=0, time_limit_s=1800))
def calibrate_station(job_id: str) -> dict[str, Any]:
    """Place every head (and thermal camera) of the job's station calibration set in one world frame from the
    uploaded board views (``params["views"]``: per head or thermal camera, ``[digest, suffix, file name]``), and
    store the result as a new calibration set with the station calibration report."""
    runtime = current_runtime()
    params = _job(runtime, job_id).params
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    board = parse_board(runtime.store.read_bytes(params["board"]).decode(), f"artifact {params['board']}")
    views = {key: [(label, uploaded_board_image(runtime.store.read_bytes(digest), suffix=suffix,
                                                source=f"{key}/{label}")) for digest, suffix, label in uploads]
             for key, uploads in params["views"].items()}
    runtime.tracker.progress(job_id, "calibrate", 0.3)
    outcome = calibrate_station_views(board=board, rig=rig, views=views, world=params["world"],
                                      intrinsics=params["intrinsics"], source=f"job {job_id}")
    rig_digest = runtime.store.put_bytes(rig_to_json(outcome.rig).encode())
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name=params["name"], station=params["station"], rig_sha256=rig_digest,
                                     source="calibration")
        session.add(calibration)
        session.flush()
        if params["activate"]:
            activate_calibration(session, calibration)
        calibration_id = calibration.id
    report_json = outcome.report.model_dump_json(indent=2).encode()
    return {"calibration_set_id": calibration_id,
            "artifacts": {"rig.json": rig_digest, "station.json": runtime.store.put_bytes(report_json)}}


ACTORS = {actor.actor_name: actor for actor in (scan, reconstruct, fuse, register, calibrate, calibrate_station)}


def warm_up_runtime(runtime: Runtime) -> None:
    """Warm this process up for the station's active calibration and the gateway's sequence (see
    :func:`services.pipeline.warmup.warm_up`), then mark the runtime ready. Without an active calibration
    or a gateway only the kernels are warmed (with the simulated rig)."""
    try:
        with runtime.sessions() as session:
            calibration = session.scalar(select(CalibrationSet).where(
                CalibrationSet.station == runtime.settings.station, CalibrationSet.active.is_(True)))
        rig = forging_rig() if calibration is None else _calibration_rig(runtime, calibration.id)
        try:
            with GatewayClient(runtime.settings.gateway_url, timeout_s=10) as gateway:
                sequence = gateway.sequence()
        except GatewayError as error:
            logger.warning("warm-up without the gateway's sequence (%s): the default one", error)
            sequence = generate_sequence(*rig.device(None, "projector")[1].size)[0]
        seconds = warm_up(rig=rig, sequence=sequence, tables=runtime.tables)
        logger.info("warmed up in %s s", seconds)
    except Exception:  # a failed warm-up only costs the first scan its speed
        logger.exception("warm-up failed; the first scan will compile what it needs")
    finally:
        runtime.ready.set()


def _uploaded_images(store: ArtifactStore, uploads: list[list[str]], what: str) -> list[tuple[str, np.ndarray]]:
    """The board images of uploaded files: a thermal device's radiometric files (FLIR R-JPEG, float TIFF) are
    stretched from degrees C; 8- and 16-bit images are used as they are."""
    return [(f"{what} {index}", uploaded_board_image(store.read_bytes(digest), suffix=suffix,
                                                     source=f"{what} {index} ({suffix})"))
            for index, (digest, suffix) in enumerate(uploads)]


def _job(runtime: Runtime, job_id: str) -> Job:
    with runtime.sessions() as session:
        return session.get(Job, job_id)


def _scan_artifacts(runtime: Runtime, scan_id: str) -> dict[str, str]:
    with runtime.sessions() as session:
        return dict(session.get(Scan, scan_id).artifacts)


def _part_type(runtime: Runtime, part_type_id: str):
    with runtime.sessions() as session:
        part_type = session.get(PartType, part_type_id)
    return runtime.part_type(part_type.part_sha256, part_type.mesh_sha256, f"part type {part_type_id}")


def _calibration_rig(runtime: Runtime, calibration_set_id: str) -> Rig:
    with runtime.sessions() as session:
        digest = session.get(CalibrationSet, calibration_set_id).rig_sha256
    return runtime.rig(digest, f"calibration set {calibration_set_id}")


def _load_npy(store: ArtifactStore, digest: str) -> np.ndarray:
    return np.load(store.path(digest), allow_pickle=False)


def _load_sequence(store: ArtifactStore, digest: str) -> Sequence:
    return parse_sequence(store.read_bytes(digest).decode(), f"artifact {digest}")
