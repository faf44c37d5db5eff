"""Dramatiq actors: plain functions that load their job's inputs, call ``services/`` and store the outputs.

Each actor takes a job id; its parameters are the job row's ``params`` and its
return value becomes the job's ``result`` (via the JobBookkeeping middleware).
Retries and time limits are set per actor: device and network trouble is retried,
bad input (``ValueError``, including ``InputError``) is not.
"""

from __future__ import annotations

import io
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Any

import dramatiq
import numpy as np

from device_gateway.client import GatewayClient
from services.db.models import CalibrationSet, Job, Scan
from services.formats.ply import write_cloud
from services.formats.rig import Rig, parse_rig
from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.geometry.camera import camera_center
from services.storage.artifacts import ArtifactStore
from services.streaming.proxy import proxy_url
from services.streaming.recording import StationView, scan_recording
from services.structured_light.reconstruct import reconstruct_points
from services.structured_light.triangulate import camera_ray_table
from workers.runtime import Runtime, current_runtime
from workers.summary import field_summary

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
    camera_name, camera = rig.device(None, "camera")
    _, projector = rig.device(None, "projector")
    thermal_name, thermal = rig.device(None, "thermal")
    stages = _Stages(runtime, job_id)

    with stages("capture", 0.05), GatewayClient(settings.gateway_url) as gateway:
        capture = gateway.capture(thermal_frames=1)
    with stages("reconstruct", 0.3):
        cloud = reconstruct_points(capture.frames, capture.sequence, camera, projector,
                                   rays=_ray_table(rig_digest, camera_name, rig))
    with stages("fuse", 0.55):
        field = temperature_field(cloud, [ThermalView(thermal, capture.thermal)],
                                  camera_center(camera.R_array, camera.t_array))
    with stages("store", 0.7):
        artifacts = {
            "cloud.ply": _store_cloud(store, cloud),
            "field.ply": _store_cloud(store, field),
            "frames.npy": store.put_bytes(_npy(capture.frames)),
            "thermal.npy": store.put_bytes(_npy(capture.thermal.astype(np.float32))),
        }
    with stages("stream", 0.85):
        captured_at = float(capture.frame_timestamps[0]) if len(capture.frame_timestamps) else None
        artifacts["field.rrd"] = store.put_bytes(
            scan_recording(params["scan_id"], field, rig, capture.thermal[0], captured_at))
        _station_view(settings.rerun_host, settings.rerun_port, settings.station).publish(
            field, rig, capture.thermal[0], captured_at)
    summary = field_summary(field)
    with runtime.sessions.begin() as session:
        row = session.get(Scan, params["scan_id"])
        row.artifacts, row.summary = artifacts, summary
    return {"scan_id": params["scan_id"], "artifacts": artifacts, "thermal_device": thermal_name,
            "stage_seconds": stages.seconds}


ACTORS = {"scan": scan}


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


def _calibration_rig(runtime: Runtime, calibration_set_id: str) -> tuple[str, Rig]:
    with runtime.sessions() as session:
        calibration = session.get(CalibrationSet, calibration_set_id)
        digest = calibration.rig_sha256
    return digest, parse_rig(runtime.store.read_bytes(digest).decode(), f"calibration set {calibration_set_id}")


_ray_tables: dict[tuple[str, str], np.ndarray] = {}


def _ray_table(rig_digest: str, camera_name: str, rig: Rig) -> np.ndarray:
    """The camera's undistorted ray table, computed once per calibration and process (it is the slow part)."""
    if (rig_digest, camera_name) not in _ray_tables:
        camera = rig.devices[camera_name]
        _ray_tables[rig_digest, camera_name] = camera_ray_table(camera.K_array, camera.dist_array,
                                                                camera.width, camera.height)
    return _ray_tables[rig_digest, camera_name]


@lru_cache(maxsize=1)
def _station_view(host: str, port: int, station: str) -> StationView:
    return StationView(proxy_url(host, port), station)


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
