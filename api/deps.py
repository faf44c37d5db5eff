"""Typed dependencies shared by the routers: the runtime, a database session and the caller's API key."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from api.problems import Problem
from services.db.apikeys import find_api_key, grants
from services.db.models import ApiKey
from workers.runtime import Runtime

_bearer = HTTPBearer(auto_error=False, description="An API key made by `thermofield apikey create`.")


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]


def get_session(runtime: RuntimeDep) -> Iterator[Session]:
    with runtime.sessions() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


def get_current_key(
    session: SessionDep, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> ApiKey:
    challenge = {"WWW-Authenticate": "Bearer"}
    if credentials is None:
        raise Problem(401, "unauthenticated", "Send an API key as 'Authorization: Bearer <key>'.", challenge)
    key = find_api_key(session, credentials.credentials)
    if key is None:
        raise Problem(401, "unauthenticated", "The API key is unknown or revoked.", challenge)
    return key


CurrentKey = Annotated[ApiKey, Depends(get_current_key)]


def _require(scope: str) -> Callable[[ApiKey], ApiKey]:
    def check(key: CurrentKey) -> ApiKey:
        if not grants(key, scope):
            raise Problem(403, "forbidden", f"This API key lacks the '{scope}' scope (it has: {key.scopes}).")
        return key

    return check


ReaderKey = Annotated[ApiKey, Depends(_require("read"))]
OperatorKey = Annotated[ApiKey, Depends(_require("operate"))]
AdminKey = Annotated[ApiKey, Depends(_require("admin"))]
