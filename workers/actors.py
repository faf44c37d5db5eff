"""Dramatiq actors: each translates its message (a job id) into its use case in ``services.pipeline.jobs``.

Each actor takes a job id; the use case reads the job row's ``params`` and its return value becomes the
job's ``result`` (via the JobBookkeeping middleware): ``{"artifacts": {name: digest}, ...}``. The actors
query and write no rows themselves. Retries and time limits are set per actor: device and network trouble
is retried, bad input (``ValueError``, including ``InputError``) and a full artifact store (``StorageFull``)
are not.

- ``scan``: capture with the gateway, reconstruct, fuse, inspect (with a part type), store, stream, summarise; on
  a station of several heads: capture, store, then ``scan_head`` per head as one group whose completion sends
  ``scan_merge`` (merge, fuse, inspect, store, stream), which finishes the scan job.
- ``reconstruct``, ``fuse``, ``register``: one step again on a stored scan, e.g. with
  another calibration set (reconstruct then fuse its cloud) or to check the thermal
  camera's alignment by mutual information (register).
- ``calibrate``: a new calibration set with a device re-placed from paired board images, uploaded or
  filmed by the gateway (a calibration capture job).
"""

from __future__ import annotations

import logging
import threading
from typing import Any

import dramatiq

from device_gateway.client import GatewayClient, GatewayError
from device_gateway.station import BoardViews, Capture
from services.jobs.tracker import CONTINUATION
from services.pipeline import jobs
from services.pipeline.warmup import warm_up
from services.runtime import Runtime, current_runtime
from services.simulation.presets import forging_rig
from services.storage.artifacts import StorageFull
from services.structured_light.patterns import generate_sequence

logger = logging.getLogger(__name__)
_NOT_RETRIED = (ValueError, StorageFull)  # bad input; a full artifact disk (retrying at once cannot help)


def _options(max_retries: int, time_limit_s: float) -> dict[str, Any]:
    return {"max_retries": max_retries, "time_limit": int(time_limit_s * 1000),
            "min_backoff": 500, "max_backoff": 10_000, "throws": _NOT_RETRIED}


@dramatiq.actor(actor_name="scan", **_options(max_retries=2, time_limit_s=120))
def scan(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.scan_job` with the gateway's capture."""
    runtime = current_runtime()

    def capture() -> Capture:
        try:
            with GatewayClient(runtime.settings.gateway_url) as gateway:
                return gateway.capture(thermal_frames=1, exposure=runtime.settings.camera_exposure_mode)
        except GatewayError as error:  # the job's error says which stage lost the devices
            raise GatewayError(f"capture failed: {error}", error.status) from None

    return jobs.scan_job(runtime=runtime, job_id=job_id, capture=capture, dispatch=_dispatch_heads)


def _dispatch_heads(head_jobs: list[str], scan_job: str) -> None:
    """A station scan's heads as one group, one message each; its completion continues the scan (merge)."""
    heads = dramatiq.group([scan_head.message(head_job) for head_job in head_jobs])
    heads.add_completion_callback(scan_merge.message_with_options(args=(scan_job,), **{CONTINUATION: True}))
    heads.run()


@dramatiq.actor(actor_name="scan_head", **_options(max_retries=2, time_limit_s=120))
def scan_head(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.scan_head_job`: one head of a station scan."""
    return jobs.scan_head_job(runtime=current_runtime(), job_id=job_id)


@dramatiq.actor(actor_name="scan_merge", **_options(max_retries=2, time_limit_s=120))
def scan_merge(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.scan_merge_job`: a station scan's merge, field, inspection and storing, once
    its heads are done (the scan job's continuation)."""
    return jobs.scan_merge_job(runtime=current_runtime(), job_id=job_id)


@dramatiq.actor(actor_name="reconstruct", **_options(max_retries=1, time_limit_s=120))
def reconstruct(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.reconstruct_job`: the point cloud of a stored scan's frames."""
    return jobs.reconstruct_job(runtime=current_runtime(), job_id=job_id)


@dramatiq.actor(actor_name="fuse", **_options(max_retries=1, time_limit_s=120))
def fuse(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.fuse_job`: the temperature field of a stored cloud."""
    return jobs.fuse_job(runtime=current_runtime(), job_id=job_id)


@dramatiq.actor(actor_name="register", **_options(max_retries=1, time_limit_s=300))
def register(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.register_job`: a stored scan's thermal frame onto its white camera frame."""
    return jobs.register_job(runtime=current_runtime(), job_id=job_id)


@dramatiq.actor(actor_name="calibrate", **_options(max_retries=0, time_limit_s=600))
def calibrate(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.calibrate_job`, a calibration capture job's board views filmed by the
    gateway."""
    runtime = current_runtime()

    def film(board: dict[str, Any], views: int, interval_s: float) -> BoardViews:
        with GatewayClient(runtime.settings.gateway_url, timeout_s=600) as gateway:
            return gateway.board_views(board, views, interval_s)

    return jobs.calibrate_job(runtime=runtime, job_id=job_id, film=film)


@dramatiq.actor(actor_name="calibrate_station", **_options(max_retries=0, time_limit_s=1800))
def calibrate_station(job_id: str) -> dict[str, Any]:
    """:func:`services.pipeline.jobs.calibrate_station_job`: every head of a station in one world frame."""
    return jobs.calibrate_station_job(runtime=current_runtime(), job_id=job_id)


ACTORS = {actor.actor_name: actor for actor in (scan, scan_head, scan_merge, reconstruct, fuse, register, calibrate,
                                                calibrate_station)}


def warm_up_runtime(runtime: Runtime) -> None:
    """Warm this process up for the station's active calibration and the gateway's sequence (see
    :func:`services.pipeline.warmup.warm_up`), then mark the runtime ready. Without an active calibration
    or a gateway only the kernels are warmed (with the simulated rig)."""
    try:
        rig = jobs.station_rig(runtime=runtime) or forging_rig()
        try:
            with GatewayClient(runtime.settings.gateway_url, timeout_s=10) as gateway:
                sequence = gateway.sequence()
        except GatewayError as error:
            logger.warning("warm-up without the gateway's sequence (%s): the default one", error)
            sequence = generate_sequence(*rig.device(None, "projector")[1].size)[0]
        seconds = warm_up(rig=rig, sequence=sequence, tables=runtime.tables)
        logger.info("warmed up in %s s", seconds)
    except Exception:  # a failed warm-up only costs the first scan its speed
        if not threading.main_thread().is_alive():  # the process is exiting (Ctrl+C): its pools refuse work
            logger.info("warm-up stopped: the process is exiting")
        else:
            logger.exception("warm-up failed; the first scan will compile what it needs")
    finally:
        runtime.ready.set()
