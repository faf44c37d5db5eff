"""The FastAPI application: routers under ``/v1``, health at the root, problem+json errors, metrics."""

from __future__ import annotations

import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.routing import APIRoute

from services.bodylimit import BodySizeLimit
from api.decoding import DecoderPool
from api.deps import KeyCache
from api.docs import install_offline_docs
from api.metrics import ApiMetrics, MetricsMiddleware
from api.problems import install_problem_handlers, problem_responses
from api.ratelimit import RateLimiter
from api.routers import apikeys, calibrations, devices, health, jobs, parts, scans
from services.jobs.outbox import Outbox
from services.jobs.queue import JobQueue
from services.runtime import Runtime


def _operation_id(route: APIRoute) -> str:
    """Stable operation ids: the route's name (e.g. ``create_scan``), never derived from the path."""
    return route.name


def create_app(runtime: Runtime, job_queue: JobQueue) -> FastAPI:
    """The API serving ``runtime``'s database and artifact store; jobs go to ``job_queue`` (by actor name)
    through the outbox, whose thread runs while the app does (its lifespan)."""
    outbox = Outbox(runtime.sessions, job_queue)
    settings = runtime.settings
    decoders = DecoderPool(settings.decode_processes, settings.decode_memory_bytes, settings.decode_timeout_s)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        threading.Thread(target=decoders.start, name="thermofield-forkserver", daemon=True).start()
        with outbox:
            yield

    app = FastAPI(
        lifespan=lifespan,
        title="thermofield",
        version="1",
        summary="3D temperature fields of hot forgings: scans, inspection, calibration sets, part types, jobs.",
        generate_unique_id_function=_operation_id,
        # FastAPI's own OpenTelemetry hooks look the global providers up on every request; the service's
        # metrics are its Prometheus ones (api/metrics.py), so they are off
        telemetry={"tracing": False, "metrics": False, "logs": False},
        docs_url=None, redoc_url=None,  # served by install_offline_docs, without a CDN
    )
    app.state.runtime = runtime
    app.state.jobs = outbox
    app.state.decoders = decoders
    app.state.key_cache = KeyCache()
    app.state.rate_limiter = RateLimiter(runtime.settings.rate_limit_per_s, runtime.settings.rate_limit_burst)
    app.state.auth_failures = RateLimiter(settings.auth_failure_rate_per_s, settings.auth_failure_burst)
    app.state.metrics = ApiMetrics(runtime, outbox.pending)
    install_problem_handlers(app)
    app.add_middleware(BodySizeLimit, limits=lambda: (runtime.settings.max_upload_bytes,
                                                      runtime.settings.max_body_bytes))
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    # each router straight under /v1 (one level of FastAPI's route matching less than a /v1 router of routers), the
    # jobs first: the polls match at once
    for module in (jobs, scans, calibrations, parts, devices, apikeys):
        app.include_router(module.router, prefix="/v1",
                           responses=problem_responses(400, 401, 403, 413, 415, 422, 429, 503))
    app.include_router(health.router)
    install_offline_docs(app)
    return app
