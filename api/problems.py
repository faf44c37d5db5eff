"""RFC 9457 problem details (``application/problem+json``) for every error the API returns."""

from __future__ import annotations

import errno
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict
from sqlalchemy.exc import DBAPIError, OperationalError
from starlette.exceptions import HTTPException as StarletteHTTPException

from services.errors import InputError
from services.formats.limits import DeclaredSizeError
from services.problems import PROBLEM_MEDIA_TYPE, problem_response

RETRY_AFTER_S = 5  # seconds a client waits after a 503 (database or storage down, queue full)


class ProblemDetails(BaseModel):
    """RFC 9457 problem details; extensions (e.g. ``errors`` of a 422) may follow."""

    model_config = ConfigDict(extra="allow")

    type: str
    title: str
    status: int
    detail: str
    instance: str


_PROBLEM_DESCRIPTIONS = {
    400: "The request is ambiguous: two Authorization headers.",
    401: "No API key, or an unknown or revoked one.",
    403: "The API key lacks the scope.",
    404: "No such resource, or not produced yet.",
    409: "The request conflicts with the station's state.",
    413: "The request body or an uploaded file is too large.",
    415: "A JSON body sent without Content-Type: application/json.",
    422: "The request or an uploaded file is invalid.",
    429: "The API key is over its rate limit, or the client's address sent too many unknown keys; see "
         "Retry-After.",
    502: "The device gateway is unreachable.",
    503: "The database or the artifact store is unavailable, or the job queue is full; see Retry-After.",
}


def problem_responses(*statuses: int) -> dict[int, dict[str, Any]]:
    """OpenAPI ``responses`` declaring problem+json answers for ``statuses``."""
    return {status: {"description": _PROBLEM_DESCRIPTIONS[status], "model": ProblemDetails,
                     "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/ProblemDetails"}}}}
            for status in statuses}


class Problem(Exception):
    """An error answered as problem+json: ``kind`` is the last part of the ``type`` URI."""

    def __init__(self, status: int, kind: str, detail: str, headers: dict[str, str] | None = None,
                 **extensions: Any) -> None:
        super().__init__(detail)
        self.status, self.kind, self.detail = status, kind, detail
        self.headers = headers
        self.extensions = extensions


_NOT_AN_OBJECT = frozenset({"model_attributes_type", "dict_type", "model_type"})


def install_problem_handlers(app: FastAPI) -> None:
    """Turn every exception into problem+json: ours, HTTP errors, validation errors and bugs."""

    @app.exception_handler(Problem)
    async def _problem(request: Request, error: Problem) -> JSONResponse:
        return problem_response(error.status, error.kind, error.detail, request.url.path, error.headers,
                                **error.extensions)

    @app.exception_handler(InputError)
    async def _input_error(request: Request, error: InputError) -> JSONResponse:
        return problem_response(422, "invalid-input", str(error), request.url.path)

    @app.exception_handler(DeclaredSizeError)
    async def _declared_too_large(request: Request, error: DeclaredSizeError) -> JSONResponse:
        return problem_response(413, "payload-too-large", str(error), request.url.path)

    @app.exception_handler(MemoryError)
    async def _out_of_memory(request: Request, error: MemoryError) -> JSONResponse:
        return problem_response(413, "payload-too-large", "The request needs more memory than the service can "
                                                          "give it.", request.url.path)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, error: RequestValidationError) -> JSONResponse:
        content_type = request.headers.get("content-type", "")
        if "json" not in content_type.lower() and any(
                tuple(item["loc"]) == ("body",) and item["type"] in _NOT_AN_OBJECT for item in error.errors()):
            # FastAPI parses a body as JSON only when its Content-Type says so; any other body reaches the
            # model as raw bytes, whose error ("not a valid dictionary") would hide what is wrong
            detail = (f"body: a JSON body must be sent with Content-Type: application/json "
                      f"(got {content_type or 'no Content-Type'})")
            return problem_response(415, "unsupported-media-type", detail, request.url.path,
                                    errors=[{"field": "body", "message": detail.removeprefix("body: ")}])
        errors = [
            {"field": ".".join(str(part) for part in item["loc"]), "message": item["msg"]} for item in error.errors()
        ]
        detail = "; ".join(f"{item['field']}: {item['message']}" for item in errors)
        return problem_response(422, "validation-error", detail, request.url.path, errors=errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, error: StarletteHTTPException) -> JSONResponse:
        if error.status_code == 400:
            # FastAPI and Starlette answer 400 only for a body they cannot parse (not UTF-8 JSON, a broken
            # multipart form): the same fault as a body that is not JSON, which FastAPI answers 422
            detail = f"body: {error.detail}" + (f" ({type(error.__cause__).__name__})" if error.__cause__ else "")
            return problem_response(422, "validation-error", detail, request.url.path,
                                    errors=[{"field": "body", "message": detail.removeprefix("body: ")}])
        kind = HTTPStatus(error.status_code).phrase.lower().replace(" ", "-")
        return problem_response(error.status_code, kind, str(error.detail), request.url.path,
                                getattr(error, "headers", None))

    @app.exception_handler(DBAPIError)
    async def _database_down(request: Request, error: DBAPIError) -> JSONResponse:
        if not (isinstance(error, OperationalError) or error.connection_invalidated):
            return await _bug(request, error)
        return problem_response(503, "database-unavailable", "The database is unavailable; retry shortly.",
                                request.url.path, {"Retry-After": str(RETRY_AFTER_S)})

    @app.exception_handler(OSError)
    async def _storage(request: Request, error: OSError) -> JSONResponse:
        if error.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
            return await _bug(request, error)
        return problem_response(503, "storage-full", "The artifact store cannot take more data now; retry "
                                                     "later.", request.url.path, {"Retry-After": str(RETRY_AFTER_S)})

    @app.exception_handler(Exception)
    async def _bug(request: Request, error: Exception) -> JSONResponse:
        return problem_response(500, "internal-error", f"An internal error occurred ({type(error).__name__}).",
                                request.url.path)
