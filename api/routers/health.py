"""Liveness, readiness and Prometheus metrics (no API key needed)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from sqlalchemy import text

from api.deps import RuntimeDep
from api.problems import Problem
from api.schemas import Health, Readiness

router = APIRouter(tags=["health"])


@router.get("/healthz", name="get_health")
def get_health() -> Health:
    """The process is up."""
    return Health(status="ok")


@router.get("/readyz", name="get_readiness", responses={503: {"description": "A dependency is down."}})
def get_readiness(runtime: RuntimeDep) -> Readiness:
    """The database answers and its schema is migrated."""
    try:
        with runtime.engine.connect() as connection:
            revision = connection.execute(text("SELECT version_num FROM alembic_version")).scalar_one()
    except Exception as error:  # any driver error means not ready
        raise Problem(503, "not-ready", f"The database is not ready: {type(error).__name__}.")
    return Readiness(status="ready", checks={"database": f"ok (schema revision {revision})"})


@router.get("/metrics", name="get_metrics", response_class=Response,
            responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}})
def get_metrics(request: Request) -> Response:
    """Prometheus metrics: requests, latencies, jobs by status."""
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
