"""Liveness, readiness and Prometheus metrics (no API key needed)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from api.deps import RuntimeDep
from api.problems import RETRY_AFTER_S, Problem, problem_responses
from api.schemas import Health, Readiness
from services.db.engine import schema_revision

router = APIRouter(tags=["health"])


@router.get("/healthz", name="get_health")
def get_health() -> Health:
    """The process is up."""
    return Health(status="ok")


@router.get("/readyz", name="get_readiness", responses=problem_responses(503))
def get_readiness(runtime: RuntimeDep) -> Readiness:
    """The database answers and its schema is migrated; the artifact store is writable with room for scans; the
    embedded worker has warmed up."""
    retry = {"Retry-After": str(RETRY_AFTER_S)}
    if not runtime.ready.is_set():
        raise Problem(503, "not-ready", "The service is warming up (compiling kernels, building the active "
                                        "calibration's tables); try again in a few seconds.", retry)
    try:
        revision = schema_revision(runtime.engine)
    except Exception as error:  # any driver error means not ready
        raise Problem(503, "not-ready", f"The database is not ready: {type(error).__name__}.", retry)
    free = runtime.store.free_bytes()
    if free < runtime.settings.min_free_bytes:
        raise Problem(503, "not-ready", f"The artifact store has {free / 1e6:.0f} MB free, less than the "
                                        f"{runtime.settings.min_free_bytes / 1e6:.0f} MB scans need.", retry)
    if not runtime.store.writable():
        raise Problem(503, "not-ready", "The artifact store cannot be written to.", retry)
    return Readiness(status="ready", checks={"database": f"ok (schema revision {revision})",
                                             "artifact_store": f"ok ({free / 1e9:.1f} GB free)"})


@router.get("/metrics", name="get_metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def get_metrics(request: Request) -> Response:
    """Prometheus metrics: requests, latencies, jobs by status."""
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
