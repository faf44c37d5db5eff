"""RFC 9457 problem details (``application/problem+json``), the error body of every HTTP service here."""

from __future__ import annotations

from http import HTTPStatus
from typing import Any

from fastapi.responses import JSONResponse

PROBLEM_MEDIA_TYPE = "application/problem+json"
PROBLEM_TYPE_BASE = "https://thermofield.example/problems/"


def problem_response(status: int, kind: str, detail: str, instance: str | None = None,
                     headers: dict[str, str] | None = None, **extensions: Any) -> JSONResponse:
    """A problem document: ``type`` is :data:`PROBLEM_TYPE_BASE` + ``kind`` (e.g. ``not-found``), ``title``
    the status's phrase; ``extensions`` are added members (e.g. ``errors``)."""
    body = {"type": PROBLEM_TYPE_BASE + kind, "title": HTTPStatus(status).phrase, "status": status,
            "detail": detail, **({} if instance is None else {"instance": instance}), **extensions}
    return JSONResponse(body, status_code=status, media_type=PROBLEM_MEDIA_TYPE, headers=headers)
