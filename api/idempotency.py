"""``Idempotency-Key`` on POSTs: a retried request gets the first response; the same key with
another request is refused (422). Records are kept per API key in the database for
``THERMOFIELD_IDEMPOTENCY_TTL_S`` (after that the key may be used afresh; the periodic
maintenance deletes the expired records)."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Annotated, Any

from fastapi import Header, Request
from fastapi.responses import JSONResponse
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from api.problems import Problem
from services.db.models import ApiKey, IdempotencyRecord

IdempotencyKeyHeader = Annotated[
    str | None,
    Header(alias="Idempotency-Key", max_length=255, description="Makes a retried POST return the first response."),
]


@dataclass
class Outcome:
    """A POST's answer, and what to do once its database changes are committed (e.g. enqueue a job)."""

    status: int
    body: dict[str, Any]
    location: str | None = None
    after_commit: Callable[[], None] | None = None


def request_digest(request: Request, content: bytes) -> str:
    """SHA-256 of the method and path of ``request`` and its ``content`` (the body, or the parsed form)."""
    hasher = hashlib.sha256(f"{request.method} {request.url.path}\n".encode())
    hasher.update(content)
    return hasher.hexdigest()


def respond_once(
    session: Session, key: ApiKey, idempotency_key: str | None, digest: str, produce: Callable[[], Outcome],
    ttl_s: float,
) -> JSONResponse:
    """Commit and answer ``produce()``'s outcome, or replay the answer stored under the idempotency key.

    The outcome's rows and the idempotency record are committed together, so a
    retry can never create a second job.
    """
    if idempotency_key is not None:
        replay = _stored_response(session, key, idempotency_key, digest, ttl_s)
        if replay is not None:
            return replay
    outcome = produce()
    if idempotency_key is not None:
        session.add(IdempotencyRecord(api_key_id=key.id, key=idempotency_key, request_sha256=digest,
                                      status_code=outcome.status, location=outcome.location,
                                      body=json.dumps(outcome.body)))
    try:
        session.commit()
    except IntegrityError:
        if idempotency_key is None:
            raise
        session.rollback()  # a concurrent retry stored its answer first
        return _stored_response(session, key, idempotency_key, digest, ttl_s)
    if outcome.after_commit is not None:
        outcome.after_commit()
    headers = {"Location": outcome.location} if outcome.location else None
    return JSONResponse(outcome.body, status_code=outcome.status, headers=headers)


def _stored_response(session: Session, key: ApiKey, idempotency_key: str, digest: str,
                     ttl_s: float) -> JSONResponse | None:
    record = session.scalar(
        select(IdempotencyRecord).where(IdempotencyRecord.api_key_id == key.id,
                                        IdempotencyRecord.key == idempotency_key)
    )
    if record is None:
        return None
    created = record.created_at if record.created_at.tzinfo else record.created_at.replace(tzinfo=UTC)
    if created < datetime.now(UTC) - timedelta(seconds=ttl_s):
        session.delete(record)  # expired: the key starts afresh (deleted with the new answer's commit)
        session.flush()
        return None
    if record.request_sha256 != digest:
        raise Problem(422, "idempotency-key-reused",
                      f"Idempotency-Key {idempotency_key!r} was already used with a different request.")
    headers = {"Location": record.location} if record.location else {}
    headers["Idempotent-Replayed"] = "true"
    return JSONResponse(json.loads(record.body), status_code=record.status_code, headers=headers)
