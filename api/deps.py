"""Typed dependencies shared by the routers: the runtime, the job queue, a database session and the caller's
API key.

Dependencies that do no I/O are ``async`` so that FastAPI does not hand each of them to
a worker thread; database queries run in the thread pool. Authenticated keys are
cached for a few seconds, which spares a query on every poll of a job; unknown keys are
cached too (negatively), and concurrent requests with one key share one query, so that a
flood of made-up keys costs at most one query per distinct key. Failed authentications
are rate-limited per client address.
"""

from __future__ import annotations

import asyncio
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
UNKNOWN_KEY_CACHE_SECONDS = 5.0
_MAX_CACHED = 10_000
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
    """Recently authenticated keys by secret digest (a revoked key stops working within the cache time), and
    recently unknown digests (a key created meanwhile cannot be among them: its secret was never sent)."""

    def __init__(self, seconds: float = KEY_CACHE_SECONDS, unknown_seconds: float = UNKNOWN_KEY_CACHE_SECONDS) -> None:
        self.seconds, self.unknown_seconds = seconds, unknown_seconds
        self._keys: dict[str, tuple[float, ApiKey]] = {}
        self._unknown: dict[str, float] = {}
        self._pending: dict[str, asyncio.Future] = {}

    def get(self, digest: str) -> ApiKey | None:
        entry = self._keys.get(digest)
        if entry is None or entry[0] < time.monotonic():
            return None
        return entry[1]

    def put(self, digest: str, key: ApiKey) -> None:
        if len(self._keys) > _MAX_CACHED:
            self._keys.clear()
        self._keys[digest] = (time.monotonic() + self.seconds, key)

    def evict(self, key_id: str) -> None:
        """Forget ``key_id`` at once (it was revoked through this process)."""
        self._keys = {digest: entry for digest, entry in self._keys.items() if entry[1].id != key_id}

    async def lookup(self, digest: str, find: Callable[[], Awaitable[ApiKey | None]]) -> ApiKey | None:
        """The key of ``digest`` from the cache, else from ``find()`` (the database), which runs once for all
        the requests asking at the same time; an unknown digest is remembered for ``unknown_seconds``."""
        key = self.get(digest)
        if key is not None:
            return key
        if self._unknown.get(digest, 0.0) >= time.monotonic():
            return None
        pending = self._pending.get(digest)
        if pending is None:
            pending = self._pending[digest] = asyncio.ensure_future(self._find(digest, find))
        return await asyncio.shield(pending)  # a client leaving does not cancel the others' query

    async def _find(self, digest: str, find: Callable[[], Awaitable[ApiKey | None]]) -> ApiKey | None:
        try:
            key = await find()
        finally:
            del self._pending[digest]
        if key is None:
            if len(self._unknown) > _MAX_CACHED:
                now = time.monotonic()
                self._unknown = {known: until for known, until in self._unknown.items() if until >= now}
                if len(self._unknown) > _MAX_CACHED:
                    self._unknown.clear()
            self._unknown[digest] = time.monotonic() + self.unknown_seconds
        else:
            self.put(digest, key)
        return key


async def _authenticate(request: Request, credentials: HTTPAuthorizationCredentials | None) -> ApiKey:
    """The caller's key, from the cache or the database; 400 for two ``Authorization`` headers, 401 for none
    or an unknown or revoked key, 429 over its rate limit or, before any lookup, when the client's address
    failed too often. Once per request (a route may need two scopes' checks, e.g. its own and its
    resource's), so that a request takes one token of the key's rate limit."""
    authenticated = getattr(request.state, "api_key", None)
    if authenticated is not None:
        return authenticated
    challenge = {"WWW-Authenticate": "Bearer"}
    copies = len(request.headers.getlist("authorization"))
    if copies > 1:  # a proxy reading the last copy and the service reading the first would disagree on who it is
        raise Problem(400, "ambiguous-credentials", f"Send one Authorization header; this request has {copies}.")
    if credentials is None:
        raise Problem(401, "unauthenticated", "Send an API key as 'Authorization: Bearer <key>'.", challenge)
    runtime: Runtime = request.app.state.runtime
    cache: KeyCache = request.app.state.key_cache
    digest = secret_digest(credentials.credentials)
    key = cache.get(digest)
    if key is None:
        failures = request.app.state.auth_failures
        address = request.client.host if request.client else "unknown"
        wait = failures.wait_seconds(address)  # taken before the lookup, so that a flood all at once is held
        if wait:  # off too; given back when the key is good
            raise Problem(429, "rate-limited", f"This client address sent more than "
                                               f"{runtime.settings.auth_failure_burst} unknown or revoked API keys; "
                                               f"retry in {wait} s.", {"Retry-After": str(wait)})
        key = await cache.lookup(digest, lambda: run_in_threadpool(_find_key, runtime, credentials.credentials))
        if key is not None:
            failures.refund(address)
        if key is None:
            raise Problem(401, "unauthenticated", "The API key is unknown or revoked.", challenge)
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
