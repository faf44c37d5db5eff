"""The FastAPI application: routers under ``/v1``, health at the root, problem+json errors, metrics."""

from __future__ import annotations

from fastapi import APIRouter, FastAPI
from fastapi.routing import APIRoute

from api.deps import KeyCache
from api.metrics import ApiMetrics, MetricsMiddleware
from api.problems import install_problem_handlers, problem_responses
from api.ratelimit import RateLimiter
from api.routers import apikeys, calibrations, devices, health, jobs, parts, scans
from services.jobs.queue import JobQueue
from services.runtime import Runtime


def _operation_id(route: APIRoute) -> str:
    """Stable operation ids: the route's name (e.g. ``create_scan``), never derived from the path."""
    return route.name


def create_app(runtime: Runtime, job_queue: JobQueue) -> FastAPI:
    """The API serving ``runtime``'s database and artifact store; jobs go to ``job_queue`` (by actor name)."""
    app = FastAPI(
        title="thermofield",
        version="1",
        summary="3D temperature fields of hot forgings: scans, inspection, calibration sets, part types, jobs.",
        generate_unique_id_function=_operation_id,
    )
    app.state.runtime = runtime
    app.state.jobs = job_queue
    app.state.key_cache = KeyCache()
    app.state.rate_limiter = RateLimiter(runtime.settings.rate_limit_per_s, runtime.settings.rate_limit_burst)
    app.state.metrics = ApiMetrics(runtime)
    install_problem_handlers(app)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    app.include_router(health.router)
    v1 = APIRouter(prefix="/v1", responses=problem_responses(401, 403, 422, 429, 503))
    for module in (scans, jobs, calibrations, parts, devices, apikeys):
        v1.include_router(module.router)
    app.include_router(v1)
    return app
