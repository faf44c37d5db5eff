"""Prometheus metrics of one API process: requests and latencies per operation, jobs by status, jobs waiting in
the outbox."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.db.models import JOB_STATUSES, Job
from services.runtime import Runtime


class _JobsByStatus(Collector):
    """Counts the jobs table at scrape time, so every API replica reports the same truth."""

    def __init__(self, runtime: Runtime, outbox_pending: Callable[[], int]) -> None:
        self.runtime, self.outbox_pending = runtime, outbox_pending

    def collect(self) -> Iterator[GaugeMetricFamily]:
        family = GaugeMetricFamily("thermofield_jobs", "Jobs in the database by status.", labels=["status"])
        with self.runtime.sessions() as session:
            counts = dict(session.execute(select(Job.status, func.count()).group_by(Job.status)).all())
        for status in JOB_STATUSES:
            family.add_metric([status], counts.get(status, 0))
        yield family
        yield GaugeMetricFamily("thermofield_jobs_undispatched", "Jobs whose message waits in the outbox (the broker "
                                "is down or refused it).", value=self.outbox_pending())


class ApiMetrics:
    def __init__(self, runtime: Runtime, outbox_pending: Callable[[], int]) -> None:
        self.registry = CollectorRegistry()
        self.requests = Counter("thermofield_http_requests", "HTTP requests answered.",
                                ["method", "operation", "status"], registry=self.registry)
        self.latency = Histogram("thermofield_http_request_duration_seconds", "Time to answer an HTTP request.",
                                 ["method", "operation"], registry=self.registry,
                                 buckets=(0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 10))
        self.registry.register(_JobsByStatus(runtime, outbox_pending))


class MetricsMiddleware:
    """Pure ASGI middleware (cheaper than BaseHTTPMiddleware) counting and timing requests by operation id."""

    def __init__(self, app: ASGIApp, metrics: ApiMetrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def record_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, record_status)
        finally:
            operation = getattr(scope.get("route"), "name", "unmatched")
            self.metrics.requests.labels(scope["method"], operation, str(status)).inc()
            self.metrics.latency.labels(scope["method"], operation).observe(time.perf_counter() - start)
