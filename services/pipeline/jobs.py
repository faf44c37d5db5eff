"""Use cases: the service's jobs as the workers run them, one keyword-only function per job.

Each reads its job's rows (through ``services/db``) and stored files, runs the job's use case, stores its
outputs, writes the rows it makes and returns the job's JSON-safe result (``{"artifacts": {name: digest},
...}``, recorded by the job tracker). The workers' actors only translate a message into a call; what needs
the devices (a capture, the board views of a calibration capture) is given as a function, the gateway
client's, so that this layer imports no shell.

- :func:`scan_job`: capture, then :func:`services.pipeline.scan.scan_capture` and its result; a station of
  several heads: :func:`station_scan_job` (one :func:`scan_head_job` message per head, as a group whose
  completion runs :func:`scan_merge_job`).
- :func:`reconstruct_job`, :func:`fuse_job`, :func:`register_job`: one step again on a stored scan.
- :func:`calibrate_job`: a device re-placed from paired board images (uploaded or filmed), stored as a new
  calibration set.
- :func:`calibrate_station_job`: every head (and thermal camera) of a station placed in one world frame
  from uploaded board views, stored as a new calibration set.
- :func:`station_rig`: the rig of the station's active calibration set (for the warm-up).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from services.db.calibrations import active_calibration, add_calibration_set, calibration_set
from services.db.jobs import add_child_jobs, job_params, job_results
from services.db.parts import part_type
from services.db.scans import scan_artifacts
from services.errors import InputError
from services.formats.board import parse_board
from services.formats.images import png_bytes
from services.formats.ply import cloud_from_ply, cloud_to_ply
from services.formats.registration import registration_json
from services.formats.rig import Rig, rig_to_json
from services.formats.sequence import Sequence, parse_sequence
from services.formats.station_capture import HeadFrames
from services.formats.stored_scan import (CLOUD, EXPOSURE, FIELD, FRAMES, OVERLAP_SAMPLE, SEQUENCE, THERMAL,
                                          exposure_from_bytes, head_artifact, overlap_sample_bytes,
                                          overlap_sample_from_bytes, thermal_artifact)
from services.jobs.tracker import CONTINUED
from services.pipeline.calibrate import calibrate_station, place_device, thermal_board_image, uploaded_board_image
from services.pipeline.field import fuse_field
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.register import register_scan
from services.pipeline.scan import StageClock, scan_capture, scan_result
from services.pipeline.station import HeadScan, scan_head, station_capture_artifacts, store_station_scan
from services.pipeline.summary import field_summary, glow_summary
from services.storage.artifacts import ArtifactStore, ArtifactWriter

if TYPE_CHECKING:
    from services.inspection.inspect import PreparedPart
    from services.runtime import Runtime


class Capture(Protocol):
    """What a capture gives a scan (the gateway client's ``Capture``)."""

    sequence: Sequence
    frames: np.ndarray
    frame_timestamps: np.ndarray
    thermal: np.ndarray
    exposure: dict[str, Any]


class BoardViews(Protocol):
    """Paired board views filmed for a calibration (the gateway client's ``BoardViews``)."""

    camera: np.ndarray
    thermal: np.ndarray


def scan_job(*, runtime: Runtime, job_id: str, capture: Callable[[], Capture],
             dispatch: Dispatch | None = None) -> dict[str, Any]:
    """Capture (``capture``: the gateway's, with the station's exposure), reconstruct, fuse, inspect against
    the scan's part type (if any), store the artifacts, stream to the station's live view, summarise.

    The result holds the artifact digests, the seconds each stage took and, when inspected, the verdict and
    the features (:func:`services.pipeline.scan.scan_result`); the job tracker writes the artifacts, the
    summary and the verdict onto the scan when it records it. A station of several heads (the gateway's capture
    has ``heads``) continues as :func:`station_scan_job`: its heads are sent with ``dispatch``.
    """
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    part = _part_type(runtime, params["part_type_id"]) if params.get("part_type_id") else None
    clock = StageClock(lambda stage, fraction: runtime.tracker.progress(job_id, stage, fraction))
    clock.start("capture", 0.05)
    captured = capture()
    if hasattr(captured, "heads"):  # a station of several heads: one message per head, then the merge
        if dispatch is None:
            raise InputError("a station scan needs its heads dispatched as messages")
        return station_scan_job(runtime=runtime, job_id=job_id, params=params, rig=rig, captured=captured,
                                clock=clock, dispatch=dispatch)
    if len(rig.heads) > 1:
        raise InputError(f"calibration set {params['calibration_set_id']} is a station of {len(rig.heads)} heads but "
                         "the gateway filmed one: the gateway and the active calibration are of different stations")
    captured_at = float(captured.frame_timestamps[0]) if len(captured.frame_timestamps) else None
    stored = scan_capture(scan_id=params["scan_id"], frames=captured.frames, sequence=captured.sequence,
                          thermal=captured.thermal, rig=rig, tables=runtime.tables, store=runtime.store,
                          exposure=captured.exposure, captured_at=captured_at, part=part, clock=clock,
                          publish=runtime.station_view().publish)
    return scan_result(scan_id=params["scan_id"], stored=stored, part_type_id=params.get("part_type_id"),
                       stage_seconds=clock.seconds)


Dispatch = Callable[[list[str], str], None]
"""Sends a station scan's head jobs (their ids) as one group whose completion continues the scan job (its id)."""


def station_scan_job(*, runtime: Runtime, job_id: str, params: dict[str, Any], rig: Rig, captured: Any,
                     clock: StageClock, dispatch: Dispatch) -> dict[str, Any]:
    """A station scan's first message, after its capture (``captured``: the gateway's ``StationCapture``): store
    every head's frames and the thermal frames, add one ``scan_head`` job per head that filmed and send them as
    one group (``dispatch``) whose completion runs :func:`scan_merge_job`. Returns the handed-over result (the
    job waits at stage ``heads``): the capture's artifacts, per head its job or its capture's error, and
    ``last_frame_at`` (wall-clock seconds of the capture's last frame, a head's or a thermal camera's).

    A station whose every head failed is finished at once (:func:`scan_merge_job`'s outcome, NotDecidable).
    """
    names = [head.name for head in rig.heads]
    filmed = [head.head for head in captured.heads]
    if filmed != names:
        raise InputError(f"the gateway filmed the heads {filmed} but calibration set {params['calibration_set_id']} "
                         f"has the heads {names}: the gateway and the active calibration are of different stations")
    clock.start("store capture", 0.2)
    good = [head for head in captured.heads if head.error is None]
    files = station_capture_artifacts(heads=[HeadFrames(h.head, captured.sequence, h.frames) for h in good],
                                      exposures={h.head: h.exposure for h in good}, thermal=captured.thermal)
    with ArtifactWriter(runtime.store) as writer:  # hashed, written and synced two at a time
        writer.put(files)
        artifacts = writer.digests()
    head_params = [{"scan_id": params["scan_id"], "parent_job_id": job_id, "head": head.head,
                    "calibration_set_id": params["calibration_set_id"],
                    **{key: artifacts[head_artifact(head.head, key)]
                       for key in ("frames.npy", "sequence.json", "exposure.json")}} for head in good]
    head_jobs = add_child_jobs(runtime.sessions, "scan_head", head_params)
    heads = {head.head: {"error": head.error} for head in captured.heads if head.error is not None}
    heads |= {head.head: {"job_id": head_job} for head, head_job in zip(good, head_jobs)}
    captured_at = next((float(h.frame_timestamps[0]) for h in good if len(h.frame_timestamps)), None)
    stamps = [float(t) for h in good for t in h.frame_timestamps[-1:]] + [
        float(t) for stamps in captured.thermal_timestamps.values() for t in stamps[-1:]]
    clock.stop()
    handed_over = {"scan_id": params["scan_id"], "artifacts": artifacts, "heads": heads, "captured_at": captured_at,
                   "last_frame_at": max(stamps, default=None), "stage_seconds": clock.seconds}
    if not head_jobs:
        return _finish_station_scan(runtime=runtime, job_id=job_id, params=params, rig=rig, handed_over=handed_over,
                                    head_results={})
    dispatch(head_jobs, job_id)
    return {**handed_over, CONTINUED: {"stage": "heads", "fraction": 0.3}}


def scan_head_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """One head of a station scan (its own message): its stored frames reconstructed with its camera and
    projector (:func:`services.pipeline.station.scan_head`), its cloud stored as ``heads/<head>/cloud.ply``.
    The result holds the head, its points, seconds and, when it failed (nothing decoded), ``error``."""
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    store = runtime.store
    runtime.tracker.progress(job_id, "reconstruct", 0.1)
    exposure = exposure_from_bytes(store.read_bytes(params["exposure.json"]))
    head = scan_head(frames=_load_npy(store, params["frames.npy"]), sequence=_load_sequence(store, params["sequence.json"]),
                     rig=rig, head=params["head"], tables=runtime.tables, saturation_level=exposure.saturation_level)
    artifacts = {} if head.cloud is None else {
        head_artifact(head.head, CLOUD.name): store.put_bytes(cloud_to_ply(head.cloud)),
        head_artifact(head.head, OVERLAP_SAMPLE): store.put_bytes(overlap_sample_bytes(head.sample))}
    return {"head": head.head, "artifacts": artifacts, "points": 0 if head.cloud is None else len(head.cloud),
            "seconds": head.seconds, "sample_seconds": head.sample_seconds, "error": head.error}


def scan_merge_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """The completion of a station scan job (``job_id``, taken up once every head's message finished): merge,
    fuse from every thermal camera, inspect against the part type, store, stream
    (:func:`services.pipeline.station.store_station_scan`). The result is the scan's
    (:func:`services.pipeline.scan.scan_result`) with every artifact kept, the capture's and each head's."""
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    handed_over = job_results(runtime.sessions, [job_id])[job_id]
    head_jobs = [entry["job_id"] for entry in handed_over["heads"].values() if "job_id" in entry]
    return _finish_station_scan(runtime=runtime, job_id=job_id, params=params, rig=rig, handed_over=handed_over,
                                head_results=job_results(runtime.sessions, head_jobs))


def _finish_station_scan(*, runtime: Runtime, job_id: str, params: dict[str, Any], rig: Rig,
                         handed_over: dict[str, Any], head_results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    store = runtime.store
    part = _part_type(runtime, params["part_type_id"]) if params.get("part_type_id") else None
    clock = StageClock(lambda stage, fraction: runtime.tracker.progress(job_id, stage, fraction))
    clock.start("load heads", 0.5)
    artifacts = dict(handed_over["artifacts"])
    heads = []
    for station_head in rig.heads:
        entry = handed_over["heads"][station_head.name]
        if "error" in entry:
            heads.append(HeadScan(station_head.name, None, None, entry["error"]))
            continue
        result = head_results[entry["job_id"]]
        artifacts |= result.get("artifacts", {})
        digest = result.get("artifacts", {}).get(head_artifact(station_head.name, CLOUD.name))
        if result.get("error") or digest is None:
            heads.append(HeadScan(station_head.name, None, result.get("seconds"),
                                  result.get("error") or f"head {station_head.name!r}: no cloud stored"))
            continue
        sample = result["artifacts"].get(head_artifact(station_head.name, OVERLAP_SAMPLE))
        heads.append(HeadScan(station_head.name, cloud_from_ply(store.read_bytes(digest), f"artifact {digest}"),
                              result.get("seconds"),
                              sample=None if sample is None else overlap_sample_from_bytes(store.read_bytes(sample)),
                              sample_seconds=result.get("sample_seconds")))
    thermal = {name: _load_npy(store, artifacts[thermal_artifact(name)])
               for name, device in rig.devices.items() if device.kind == "thermal"
               and thermal_artifact(name) in artifacts}
    stored = store_station_scan(scan_id=params["scan_id"], heads=heads, rig=rig, thermal=thermal, store=store,
                                part=part, clock=clock, captured_at=handed_over.get("captured_at"),
                                publish=runtime.station_view().publish)
    stored = type(stored)(stored.outcome, {**artifacts, **stored.artifacts})
    seconds = {**handed_over.get("stage_seconds", {}),
               **{f"head {h.head}": h.seconds for h in heads if h.seconds is not None},
               **{f"head {h.head} sample": h.sample_seconds for h in heads if h.sample_seconds is not None},
               **clock.seconds}
    result = scan_result(scan_id=params["scan_id"], stored=stored, part_type_id=params.get("part_type_id"),
                         stage_seconds=seconds)
    return {**result, "last_frame_at": handed_over.get("last_frame_at")}


def reconstruct_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """The point cloud of a stored scan's frames with the job's calibration set: ``cloud.ply``, its point
    count and what a hot part's glow did."""
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = scan_artifacts(runtime.sessions, params["scan_id"])
    runtime.tracker.progress(job_id, "reconstruct", 0.1)
    store = runtime.store
    exposure = exposure_from_bytes(store.read_bytes(artifacts[EXPOSURE.name]) if EXPOSURE.name in artifacts else None)
    reconstruction = reconstruct_capture(frames=_load_npy(store, artifacts[FRAMES.name]),
                                         sequence=_load_sequence(store, artifacts[SEQUENCE.name]), rig=rig,
                                         tables=runtime.tables, saturation_level=exposure.saturation_level,
                                         source=f"scan {params['scan_id']}")
    cloud = reconstruction.cloud
    glow = glow_summary(reconstruction.glow, exposure)
    return {"artifacts": {CLOUD.name: store.put_bytes(cloud_to_ply(cloud))}, "point_count": len(cloud),
            "glow": None if glow is None else glow.model_dump(mode="json")}


def fuse_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """The temperature field of a stored cloud (the scan's, or a reconstruct job's: ``cloud_sha256``) and the
    scan's thermal frames, with the job's calibration set: ``field.ply`` and its summary."""
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = scan_artifacts(runtime.sessions, params["scan_id"])
    runtime.tracker.progress(job_id, "fuse", 0.1)
    store = runtime.store
    digest = params.get("cloud_sha256") or artifacts[CLOUD.name]
    cloud = cloud_from_ply(store.read_bytes(digest), f"artifact {digest}")
    field = fuse_field(cloud=cloud, rig=rig, thermal=[(None, _load_npy(store, artifacts[THERMAL.name]))],
                       source=f"artifact {digest}")
    return {"artifacts": {FIELD.name: store.put_bytes(cloud_to_ply(field))},
            "summary": field_summary(field).model_dump(mode="json")}


def register_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """Mutual-information registration of a stored scan's thermal frame onto its white camera frame with the
    job's ``model``: ``registration.json``, ``overlay.png`` and the normalised mutual information."""
    params = job_params(runtime.sessions, job_id)
    artifacts = scan_artifacts(runtime.sessions, params["scan_id"])
    runtime.tracker.progress(job_id, "register", 0.1)
    store = runtime.store
    registration, overlay = register_scan(frames=_load_npy(store, artifacts[FRAMES.name]),
                                          sequence=_load_sequence(store, artifacts[SEQUENCE.name]),
                                          thermal=_load_npy(store, artifacts[THERMAL.name]), model=params["model"])
    return {"artifacts": {"registration.json": store.put_bytes(registration_json(registration).encode()),
                          "overlay.png": store.put_bytes(png_bytes(overlay))},
            "nmi": registration.nmi}


def calibrate_job(*, runtime: Runtime, job_id: str,
                  film: Callable[[dict[str, Any], int, float], BoardViews]) -> dict[str, Any]:
    """Place a device (e.g. the thermal camera) relative to the camera from paired board images and store the
    result as a new calibration set of the job's station (made active with ``params["activate"]``).

    The pairs are the job's uploaded images, or, for a calibration capture job (``params["capture"]``),
    board views filmed first by ``film(board, views, interval_s)`` (the gateway's). Runs the stereo
    calibration of ``thermofield calibrate stereo`` (:func:`services.pipeline.calibrate.place_device`)
    starting from the job's calibration set. The result names the new set and holds ``rig.json`` and
    ``stereo.json`` (the calibration's report).
    """
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    store = runtime.store
    board_json = store.read_bytes(params["board"])
    board = parse_board(board_json.decode(), f"artifact {params['board']}")
    if "capture" in params:
        runtime.tracker.progress(job_id, "capture", 0.05)
        views = film(json.loads(board_json), params["capture"]["views"], params["capture"]["interval_s"])
        reference = [(f"camera view {i}", frame) for i, frame in enumerate(views.camera)]
        device = [(f"{params['device']} view {i}", thermal_board_image(frame)) for i, frame in enumerate(views.thermal)]
    else:
        reference = _uploaded_images(store, params["reference_images"], "reference image")
        device = _uploaded_images(store, params["device_images"], f"{params['device']} image")
    runtime.tracker.progress(job_id, "calibrate", 0.5)
    calibrated, report = place_device(board=board, rig=rig, device=params["device"], reference_images=reference,
                                      device_images=device, source=f"job {job_id}")
    rig_digest = store.put_bytes(rig_to_json(calibrated).encode())
    with runtime.sessions.begin() as session:
        calibration_id = add_calibration_set(session, name=params["name"], station=params["station"],
                                             rig_sha256=rig_digest, source="calibration",
                                             activate=params["activate"]).id
    report_json = report.model_dump_json(indent=2).encode()
    return {"calibration_set_id": calibration_id,
            "artifacts": {"rig.json": rig_digest, "stereo.json": store.put_bytes(report_json)}}


def calibrate_station_job(*, runtime: Runtime, job_id: str) -> dict[str, Any]:
    """Place every head (and thermal camera) of the job's station calibration set in one world frame from the
    uploaded board views (``params["views"]``: per head or thermal camera, ``[digest, suffix, file name]``;
    :func:`services.pipeline.calibrate.calibrate_station`) and store the result as a new calibration set. The
    result names the set and holds ``rig.json`` and ``station.json`` (the station calibration report)."""
    params = job_params(runtime.sessions, job_id)
    rig = _calibration_rig(runtime, params["calibration_set_id"])
    store = runtime.store
    board = parse_board(store.read_bytes(params["board"]).decode(), f"artifact {params['board']}")
    views = {key: [(label, uploaded_board_image(store.read_bytes(digest), suffix=suffix, source=f"{key}/{label}"))
                   for digest, suffix, label in uploads]
             for key, uploads in params["views"].items()}
    runtime.tracker.progress(job_id, "calibrate", 0.3)
    outcome = calibrate_station(board=board, rig=rig, views=views, world=params["world"],
                                intrinsics=params["intrinsics"], source=f"job {job_id}")
    rig_digest = store.put_bytes(rig_to_json(outcome.rig).encode())
    with runtime.sessions.begin() as session:
        calibration_id = add_calibration_set(session, name=params["name"], station=params["station"],
                                             rig_sha256=rig_digest, source="calibration",
                                             activate=params["activate"]).id
    report_json = outcome.report.model_dump_json(indent=2).encode()
    return {"calibration_set_id": calibration_id,
            "artifacts": {"rig.json": rig_digest, "station.json": store.put_bytes(report_json)}}


def station_rig(*, runtime: Runtime) -> Rig | None:
    """The rig of the station's active calibration set, or None when it has none."""
    with runtime.sessions() as session:
        calibration = active_calibration(session, runtime.settings.station)
        calibration_id = None if calibration is None else calibration.id
    return None if calibration_id is None else _calibration_rig(runtime, calibration_id)


def _uploaded_images(store: ArtifactStore, uploads: list[list[str]], what: str) -> list[tuple[str, np.ndarray]]:
    """The board images of uploaded files: a thermal device's radiometric files (FLIR R-JPEG, float TIFF) are
    stretched from degrees C; 8- and 16-bit images are used as they are."""
    return [(f"{what} {index}", uploaded_board_image(store.read_bytes(digest), suffix=suffix,
                                                     source=f"{what} {index} ({suffix})"))
            for index, (digest, suffix) in enumerate(uploads)]


def _calibration_rig(runtime: Runtime, calibration_set_id: str) -> Rig:
    """The calibration set's rig, parsed once per process."""
    with runtime.sessions() as session:
        calibration = calibration_set(session, calibration_set_id)
        if calibration is None:
            raise LookupError(f"there is no calibration set {calibration_set_id!r}")
        digest = calibration.rig_sha256
    return runtime.rig(digest, f"calibration set {calibration_set_id}")


def _part_type(runtime: Runtime, part_type_id: str) -> PreparedPart:
    """The part type's part file and mesh, loaded and prepared once per process."""
    with runtime.sessions() as session:
        row = part_type(session, part_type_id)
        if row is None:
            raise LookupError(f"there is no part type {part_type_id!r}")
        files = row.part_sha256, row.mesh_sha256
    return runtime.part_type(*files, f"part type {part_type_id}")


def _load_npy(store: ArtifactStore, digest: str) -> np.ndarray:
    return np.load(store.path(digest), allow_pickle=False)


def _load_sequence(store: ArtifactStore, digest: str) -> Sequence:
    return parse_sequence(store.read_bytes(digest).decode(), f"artifact {digest}")
