"""A bound on every request body, checked before the application reads any of it and while it streams in: the
API's and the device gateway's."""

from __future__ import annotations

from collections.abc import Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.problems import problem_response


class BodySizeLimit:
    """Pure ASGI middleware answering 413 problem+json ``payload-too-large`` for a body over its limit: at once
    when ``Content-Length`` says so, else (``Transfer-Encoding: chunked``) as soon as the bytes received pass it.

    ``limits()`` gives ``(multipart, other)``: the bound of a ``multipart/form-data`` upload in all, and of
    every other body (JSON). It is read per request, so the settings in force apply.

    Written here rather than taking Starlette's ``RequestBodyLimitMiddleware``: that one answers in plain text,
    with one limit per application fixed when it is built. A body over the limit is cut by telling the
    application the client left (an exception would be turned into a 400 by FastAPI's body parsing), and
    whatever it answers then is replaced by the 413.
    """

    def __init__(self, app: ASGIApp, limits: Callable[[], tuple[int, int]]) -> None:
        self.app, self.limits = app, limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        content_type, declared, chunked = b"", b"", False
        for name, value in scope["headers"]:  # ASGI header names are lower-case
            if name == b"content-type":
                content_type = value
            elif name == b"content-length":
                declared = value
            elif name == b"transfer-encoding":
                chunked = True
        if not declared and not chunked:  # no body (most requests: the polls)
            await self.app(scope, receive, send)
            return
        multipart_limit, body_limit = self.limits()
        multipart = content_type.lower().startswith(b"multipart/form-data")
        limit, what = (multipart_limit, "A multipart upload") if multipart else (body_limit, "A request body")
        if declared.isdigit() and int(declared) > limit:
            await self._refuse(scope, receive, send, what, limit)
            return
        if not chunked:  # a body the server delivers up to its Content-Length and no further
            await self.app(scope, receive, send)
            return
        received, exceeded, response_started = 0, False, False

        async def limited_receive() -> Message:
            nonlocal received, exceeded
            if exceeded:
                return {"type": "http.disconnect"}
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    exceeded = True
                    return {"type": "http.disconnect"}
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal response_started
            if exceeded and not response_started:
                return
            response_started = response_started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception:
            if not exceeded or response_started:
                raise
        if exceeded and not response_started:
            await self._refuse(scope, receive, send, what, limit)

    @staticmethod
    async def _refuse(scope: Scope, receive: Receive, send: Send, what: str, limit: int) -> None:
        response = problem_response(413, "payload-too-large", f"{what} may have at most {limit} bytes; this one "
                                                              "has more.", scope["path"], {"Connection": "close"})
        await response(scope, receive, send)
