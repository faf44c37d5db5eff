"""Dramatiq actors: plain functions that load their job's inputs, call ``services/`` and store the outputs.

Each actor takes a job id; its parameters are the job row's ``params`` and its
return value becomes the job's ``result`` (via the JobBookkeeping middleware):
``{"artifacts": {name: digest}, ...}``. Retries and time limits are set per actor:
device and network trouble is retried, bad input (``ValueError``, including
``InputError``) is not.

- ``scan``: capture with the gateway, reconstruct, fuse, store, stream, summarise.
- ``reconstruct``, ``fuse``, ``register``: one step again on a stored scan, e.g. with
  another calibration set (reconstruct then fuse its cloud) or to check the thermal
  camera's alignment by mutual information (register).
- ``calibrate``: a new calibration set with a device re-placed from paired board images, uploaded or
  filmed by the gateway (a calibration capture job).
"""

from __future__ import annotations

import io
import json
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import dramatiq
import numpy as np

from device_gateway.client import GatewayClient
from services.db.models import CalibrationSet, Job, Scan
from services.formats.ply import read_cloud, write_cloud
from services.formats.registration import registration_to_file
from services.cli.calibrate import place_device, stereo_report_path
from services.db.calibrations import activate_calibration
from services.formats.rig import Rig, load_rig, parse_rig, rig_to_json, save_rig
from services.formats.sequence import Sequence, parse_sequence, sequence_to_json
from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.geometry.camera import camera_center
from services.registration.overlay import fused_overlay
from services.registration.register import register as register_images
from services.storage.artifacts import ArtifactStore
from services.streaming.proxy import proxy_url
from services.streaming.recording import StationView, scan_recording
from services.structured_light.reconstruct import Scan as ReconstructedScan
from services.structured_light.reconstruct import coded_axis, reconstruct_scan, rig_triangulation_table
from services.structured_light.triangulate import TriangulationTable
from workers.runtime import Runtime, current_runtime
from workers.summary import field_summary, glow_summary

_NOT_RETRIED = (ValueError,)


def _options(max_retries: int, time_limit_s: float) -> dict[str, Any]:
    return {"max_retries": max_retries, "time_limit": int(time_limit_s * 1000),
            "min_backoff": 500, "max_backoff": 10_000, "throws": _NOT_RETRIED}


@dramatiq.actor(actor_name="scan", **_options(max_retries=2, time_limit_s=120))
def scan(job_id: str) -> dict[str, Any]:
    """Capture with the gateway, reconstruct, fuse, store the artifacts, stream to Rerun, summarise.

    The result holds the artifact digests and the seconds each stage took.
    """
    runtime = current_runtime()
    store, settings = runtime.store, runtime.settings
    params = _job_params(runtime, job_id)
    rig_digest, rig = _calibration_rig(runtime, params["calibration_set_id"])
    stages = _Stages(runtime, job_id)

    with stages("capture", 0.05), GatewayClient(settings.gateway_url) as gateway:
        capture = gateway.capture(thermal_frames=1, exposure=settings.camera_exposure_mode)
    with stages("reconstruct", 0.3):
        reconstructed = _reconstruct(capture.frames, capture.sequence, rig, rig_digest, capture.exposure)
        cloud = reconstructed.cloud
    with stages("fuse", 0.55):
        field = _fuse(cloud, capture.thermal, rig)
    with stages("store", 0.7):
        artifacts = {
            "cloud.ply": _store_cloud(store, cloud),
            "field.ply": _store_cloud(store, field),
            "frames.npy": store.put_bytes(_npy(capture.frames)),
            "thermal.npy": store.put_bytes(_npy(capture.thermal.astype(np.float32))),
            "sequence.json": store.put_bytes(sequence_to_json(capture.sequence).encode()),
            "exposure.json": store.put_bytes(json.dumps(capture.exposure).encode()),
        }
    with stages("stream", 0.85):
        captured_at = float(capture.frame_timestamps[0]) if len(capture.frame_timestamps) else None
        artifacts["field.rrd"] = store.put_bytes(
            scan_recording(params["scan_id"], field, rig, capture.thermal[0], captured_at))
        _station_view(settings.rerun_host, settings.rerun_port, settings.station).publish(
            field, rig, capture.thermal[0], captured_at)
    glow = glow_summary(reconstructed.glow, capture.exposure)
    summary = {**field_summary(field), "glow": glow}
    with runtime.sessions.begin() as session:
        row = session.get(Scan, params["scan_id"])
        row.artifacts, row.summary = artifacts, summary
    return {"scan_id": params["scan_id"], "artifacts": artifacts, "stage_seconds": stages.seconds, "glow": glow}


@dramatiq.actor(actor_name="reconstruct", **_options(max_retries=1, time_limit_s=120))
def reconstruct(job_id: str) -> dict[str, Any]:
    """The point cloud of a stored scan's frames, with the job's calibration set."""
    runtime = current_runtime()
    params = _job_params(runtime, job_id)
    rig_digest, rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    runtime.tracker.progress(job_id, "reconstruct", 0.1)
    exposure = json.loads(runtime.store.path(artifacts["exposure.json"]).read_bytes()) if "exposure.json" in artifacts \
        else {}
    reconstructed = _reconstruct(_load_npy(runtime.store, artifacts["frames.npy"]),
                                 _load_sequence(runtime.store, artifacts["sequence.json"]), rig, rig_digest, exposure)
    cloud = reconstructed.cloud
    return {"artifacts": {"cloud.ply": _store_cloud(runtime.store, cloud)}, "point_count": len(cloud["x"]),
            "glow": glow_summary(reconstructed.glow, exposure)}


@dramatiq.actor(actor_name="fuse", **_options(max_retries=1, time_limit_s=120))
def fuse(job_id: str) -> dict[str, Any]:
    """The temperature field of a stored cloud (the scan's, or a reconstruct job's) and the scan's thermal frames."""
    runtime = current_runtime()
    params = _job_params(runtime, job_id)
    _, rig = _calibration_rig(runtime, params["calibration_set_id"])
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    runtime.tracker.progress(job_id, "fuse", 0.1)
    cloud = read_cloud(runtime.store.path(params.get("cloud_sha256") or artifacts["cloud.ply"]))
    field = _fuse(cloud, _load_npy(runtime.store, artifacts["thermal.npy"]), rig)
    return {"artifacts": {"field.ply": _store_cloud(runtime.store, field)}, "summary": field_summary(field)}


@dramatiq.actor(actor_name="register", **_options(max_retries=1, time_limit_s=300))
def register(job_id: str) -> dict[str, Any]:
    """Mutual-information registration of a stored scan's thermal frame onto its white camera frame."""
    runtime = current_runtime()
    params = _job_params(runtime, job_id)
    artifacts = _scan_artifacts(runtime, params["scan_id"])
    frames = _load_npy(runtime.store, artifacts["frames.npy"])
    sequence = _load_sequence(runtime.store, artifacts["sequence.json"])
    visible = frames[_white_frame_index(sequence)]
    thermal = _load_npy(runtime.store, artifacts["thermal.npy"])[0]
    runtime.tracker.progress(job_id, "register", 0.1)
    registration = register_images(visible, thermal, params["model"])
    overlay = fused_overlay(visible, thermal, registration.matrix)
    registration_json = registration_to_file(registration).model_dump_json(indent=2).encode()
    return {"artifacts": {"registration.json": runtime.store.put_bytes(registration_json),
                          "overlay.png": runtime.store.put_bytes(_png(overlay))},
            "nmi": registration.nmi}


@dramatiq.actor(actor_name="calibrate", **_options(max_retries=0, time_limit_s=600))
def calibrate(job_id: str) -> dict[str, Any]:
    """Place a device (e.g. the thermal camera) relative to the camera from paired board images.

    The pairs are the job's uploaded images, or, for a calibration capture job (``params["capture"]``),
    board views the gateway films first. Runs the stereo calibration of ``thermofield calibrate stereo``
    starting from the job's calibration set, and stores the result as a new calibration set.
    """
    runtime = current_runtime()
    params = _job_params(runtime, job_id)
    _, rig = _calibration_rig(runtime, params["calibration_set_id"])
    camera_name, _ = rig.device(None, "camera")
    board_json = runtime.store.read_bytes(params["board"])
    if "capture" in params:
        runtime.tracker.progress(job_id, "capture", 0.05)
        with GatewayClient(runtime.settings.gateway_url, timeout_s=600) as gateway:
            views = gateway.board_views(json.loads(board_json), params["capture"]["views"],
                                        params["capture"]["interval_s"])
        reference_images = [(_png(frame), ".png") for frame in views.camera]
        device_images = [(_png(_thermal_board_image(frame)), ".png") for frame in views.thermal]
    else:
        reference_images = [(runtime.store.read_bytes(digest), suffix) for digest, suffix in params["reference_images"]]
        device_images = [(runtime.store.read_bytes(digest), suffix) for digest, suffix in params["device_images"]]
    runtime.tracker.progress(job_id, "calibrate", 0.5)
    with tempfile.TemporaryDirectory() as directory:
        work = Path(directory)
        (work / "board.json").write_bytes(board_json)
        save_rig(rig, work / "rig.json")
        for device, images in ((camera_name, reference_images), (params["device"], device_images)):
            (work / "pairs" / device).mkdir(parents=True)
            for index, (content, suffix) in enumerate(images):
                (work / "pairs" / device / f"{index:03d}{suffix}").write_bytes(content)
        out = work / "out" / "rig.json"
        place_device(work / "board.json", work / "rig.json", work / "pairs", params["device"], out,
                     camera_name=camera_name)
        calibrated = load_rig(out)
        report = stereo_report_path(out, params["device"]).read_bytes()
    rig_digest = runtime.store.put_bytes(rig_to_json(calibrated).encode())
    with runtime.sessions.begin() as session:
        calibration = CalibrationSet(name=params["name"], station=params["station"], rig_sha256=rig_digest,
                                     source="calibration")
        session.add(calibration)
        session.flush()
        if params["activate"]:
            activate_calibration(session, calibration)
        calibration_id = calibration.id
    return {"calibration_set_id": calibration_id,
            "artifacts": {"rig.json": rig_digest, "stereo.json": runtime.store.put_bytes(report)}}


def _thermal_board_image(temperature: np.ndarray) -> np.ndarray:
    """A thermal frame in degrees Celsius as a 16-bit image spanning its own range, for board detection."""
    low, high = np.nanpercentile(temperature, [0.5, 99.5])
    scaled = np.clip((temperature - low) / max(high - low, 1e-6), 0.0, 1.0)
    return np.round(np.nan_to_num(scaled) * 65535).astype(np.uint16)


ACTORS = {actor.actor_name: actor for actor in (scan, reconstruct, fuse, register, calibrate)}


def _reconstruct(frames: np.ndarray, sequence: Sequence, rig: Rig, rig_digest: str,
                 exposure: dict[str, Any]) -> ReconstructedScan:
    camera_name, camera = rig.device(None, "camera")
    projector_name, projector = rig.device(None, "projector")
    axis = coded_axis(sequence.coded_axes, camera, projector)
    key = (rig_digest, camera_name, projector_name, axis)
    if key not in _triangulation_tables:
        _triangulation_tables[key] = rig_triangulation_table(camera, projector, axis)
    return reconstruct_scan(frames, sequence, camera, projector, table=_triangulation_tables[key],
                            saturation_level=exposure.get("saturation_level"))


def _fuse(cloud: dict[str, np.ndarray], thermal_frames: np.ndarray, rig: Rig) -> dict[str, np.ndarray]:
    _, camera = rig.device(None, "camera")
    _, thermal = rig.device(None, "thermal")
    viewpoint = camera_center(camera.R_array, camera.t_array)
    return temperature_field(cloud, [ThermalView(thermal, thermal_frames)], viewpoint)


class _Stages:
    """Reports each stage as the job's progress and times it."""

    def __init__(self, runtime: Runtime, job_id: str) -> None:
        self.runtime, self.job_id = runtime, job_id
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str, fraction: float) -> Iterator[None]:
        self.runtime.tracker.progress(self.job_id, name, fraction)
        start = time.perf_counter()
        yield
        self.seconds[name] = round(time.perf_counter() - start, 3)


def _job_params(runtime: Runtime, job_id: str) -> dict[str, Any]:
    with runtime.sessions() as session:
        return dict(session.get(Job, job_id).params)


def _scan_artifacts(runtime: Runtime, scan_id: str) -> dict[str, str]:
    with runtime.sessions() as session:
        return dict(session.get(Scan, scan_id).artifacts)


def _calibration_rig(runtime: Runtime, calibration_set_id: str) -> tuple[str, Rig]:
    with runtime.sessions() as session:
        digest = session.get(CalibrationSet, calibration_set_id).rig_sha256
    return digest, parse_rig(runtime.store.read_bytes(digest).decode(), f"calibration set {calibration_set_id}")


# Triangulation tables per (rig digest, camera, projector, coded axis): computed once per calibration and
# process, since they take longer than a scan.
_triangulation_tables: dict[tuple[str, str, str, str], TriangulationTable] = {}


def _white_frame_index(sequence: Sequence) -> int:
    for index, frame in enumerate(sequence.frames):
        if frame.kind == "white":
            return index
    raise ValueError("The scan's sequence has no white frame to register the thermal frame against.")


def _station_view(host: str, port: int, station: str) -> StationView:
    if (host, port, station) not in _station_views:
        _station_views[host, port, station] = StationView(proxy_url(host, port), station)
    return _station_views[host, port, station]


_station_views: dict[tuple[str, int, str], StationView] = {}


def close_station_views() -> None:
    """Send what the live station views buffered and disconnect them (before the Rerun proxy stops)."""
    for view in _station_views.values():
        view.close()
    _station_views.clear()


def _store_cloud(store: ArtifactStore, cloud: dict[str, np.ndarray]) -> str:
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "cloud.ply"
        write_cloud(path, cloud)
        return store.put_file(path)


def _npy(stack: np.ndarray) -> bytes:
    """Raw frames as one ``.npy`` (no compression: storing must not slow the scan; the API encodes on request)."""
    buffer = io.BytesIO()
    np.save(buffer, stack, allow_pickle=False)
    return buffer.getvalue()


def _load_npy(store: ArtifactStore, digest: str) -> np.ndarray:
    return np.load(store.path(digest), allow_pickle=False)


def _load_sequence(store: ArtifactStore, digest: str) -> Sequence:
    return parse_sequence(store.read_bytes(digest).decode(), f"artifact {digest}")


def _png(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("OpenCV could not encode the image as PNG.")
    return encoded.tobytes()
