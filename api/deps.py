"""Typed dependencies shared by the routers: the runtime, the job queue, a database session and the caller's
API key.

Dependencies that do no I/O are ``async`` so that FastAPI does not hand each of them to
a worker thread; database queries run in the thread pool. Authenticated keys are
cached for a few seconds, which spares a query on every poll of a job.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Annotated

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api.problems import Problem
from services.db.apikeys import find_api_key, grants, secret_digest
from services.db.models import ApiKey
from services.jobs.outbox import Outbox
from services.runtime import Runtime

KEY_CACHE_SECONDS = 5.0
_bearer = HTTPBearer(auto_error=False, description="An API key made by `thermofield apikey create`.")


async def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]


async def get_job_queue(request: Request) -> Outbox:
    return request.app.state.jobs


JobQueueDep = Annotated[Outbox, Depends(get_job_queue)]
"""The job queue as the routes see it: the outbox in front of the broker."""


async def get_session(runtime: RuntimeDep) -> AsyncIterator[Session]:
    session = runtime.sessions()
    try:
        yield session
    finally:
        await run_in_threadpool(session.close)


SessionDep = Annotated[Session, Depends(get_session)]


class KeyCache:
    """Recently authenticated keys by secret digest; a revoked key stops working within the cache time."""

    def __init__(self, seconds: float = KEY_CACHE_SECONDS) -> None:
        self.seconds = seconds
        self._keys: dict[str, tuple[float, ApiKey]] = {}

    def get(self, digest: str) -> ApiKey | None:
        entry = self._keys.get(digest)
        if entry is None or entry[0] < time.monotonic():
            return None
        return entry[1]

    def put(self, digest: str, key: ApiKey) -> None:
        if len(self._keys) > 10_000:
            self._keys.clear()
        self._keys[digest] = (time.monotonic() + self.seconds, key)

    def evict(self, key_id: str) -> None:
        """Forget ``key_id`` at once (it was revoked through this process)."""
        self._keys = {digest: entry for digest, entry in self._keys.items() if entry[1].id != key_id}


async def _authenticate(request: Request, credentials: HTTPAuthorizationCredentials | None) -> ApiKey:
    """The caller's key, from the cache or the database; 401 for none or an unknown or revoked one, 429 over
    its rate limit. Once per request (a route may need two scopes' checks, e.g. its own and its resource's),
    so that a request takes one token of the key's rate limit."""
    authenticated = getattr(request.state, "api_key", None)
    if authenticated is not None:
        return authenticated
    challenge = {"WWW-Authenticate": "Bearer"}
    if credentials is None:
        raise Problem(401, "unauthenticated", "Send an API key as 'Authorization: Bearer <key>'.", challenge)
    runtime: Runtime = request.app.state.runtime
    cache: KeyCache = request.app.state.key_cache
    digest = secret_digest(credentials.credentials)
    key = cache.get(digest)
    if key is None:
        key = await run_in_threadpool(_find_key, runtime, credentials.credentials)
        if key is None:
            raise Problem(401, "unauthenticated", "The API key is unknown or revoked.", challenge)
        cache.put(digest, key)
    wait = request.app.state.rate_limiter.wait_seconds(key.id)
    if wait:
        raise Problem(429, "rate-limited", f"This API key made more than {runtime.settings.rate_limit_per_s:g} "
                                           f"requests per second; retry in {wait} s.", {"Retry-After": str(wait)})
    request.state.api_key = key
    return key


def _find_key(runtime: Runtime, secret: str) -> ApiKey | None:
    with runtime.sessions() as session:
        return find_api_key(session, secret)


def _require(scope: str) -> Callable[..., Awaitable[ApiKey]]:
    """The dependency of a route that needs ``scope``: authentication and the scope check in one dependency
    (each dependency costs FastAPI work on every request, and every poll of a job pays it)."""

    async def check(request: Request,
                    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]) -> ApiKey:
        key = await _authenticate(request, credentials)
        if not grants(key, scope):
            raise Problem(403, "forbidden", f"This API key lacks the '{scope}' scope (it has: {key.scopes}).")
        return key

    return check


ReaderKey = Annotated[ApiKey, Depends(_require("read"))]
OperatorKey = Annotated[ApiKey, Depends(_require("operate"))]
AdminKey = Annotated[ApiKey, Depends(_require("admin"))]
