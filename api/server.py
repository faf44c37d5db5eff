"""The HTTP server of the API and the gateway: uvicorn with bounds on a request's headers and on the time its
headers and body take to arrive.

uvicorn's own options cover the idle keep-alive connection (``timeout_keep_alive``) and, with its h11
parser only, the size of the headers (``h11_max_incomplete_event_size``); its default parser, httptools,
has no bound on the headers, and neither parser bounds the time a client takes to send them or the body.
So the httptools protocol is kept (it is the faster) and given three checks here: a request's line and
headers over ``max_header_bytes`` are answered 431, headers not complete within ``header_timeout_s`` of
their first byte (or of the connection) 408, a body not complete within ``body_timeout_s`` of its headers
408; each closes the connection. In production a reverse proxy sets the same bounds in front
(docs/deployment.md).
"""

from __future__ import annotations

import asyncio
import json
from http import HTTPStatus
from typing import Any

from dataclasses import dataclass

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from services.problems import PROBLEM_MEDIA_TYPE, PROBLEM_TYPE_BASE
from services.settings import Settings


_LINGER_S, _LINGER_BYTES = 2.0, 1 << 20  # a refused connection's bytes are dropped for 2 s, at most 1 MiB


@dataclass(frozen=True)
class HttpLimits:
    """The bounds :func:`limited_protocol` enforces (``THERMOFIELD_MAX_HEADER_BYTES``, ``_HEADER_TIMEOUT_S``,
    ``_BODY_TIMEOUT_S``)."""

    max_header_bytes: int
    header_timeout_s: float
    body_timeout_s: float

    @classmethod
    def of(cls, settings: Settings) -> HttpLimits:
        return cls(settings.max_header_bytes, settings.header_timeout_s, settings.body_timeout_s)


def limited_protocol(limits: HttpLimits) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol bounded by ``limits`` (a class, as uvicorn's ``http`` option takes)."""

    class LimitedHttpProtocol(HttpToolsProtocol):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            super().__init__(*args, **kwargs)
            self._header_bytes, self._in_headers, self._deadline, self._refused = 0, True, None, False
            self._dropped = 0

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm(limits.header_timeout_s, "its headers")

        def data_received(self, data: bytes) -> None:
            if self._refused or self.transport.is_closing():  # refused: the rest is read and dropped, unparsed
                self._dropped += len(data)
                if self._dropped > _LINGER_BYTES and not self.transport.is_closing():
                    self.transport.close()
                return
            if self._in_headers:
                if self._deadline is None:  # the first byte of a request on a kept-alive connection
                    self._arm(limits.header_timeout_s, "its headers")
                self._header_bytes += len(data)
            super().data_received(data)
            if self._in_headers and self._header_bytes > limits.max_header_bytes and not self._refused:
                self._refuse(431, "request-header-fields-too-large",
                             f"A request's line and headers may have at most {limits.max_header_bytes} bytes.")

        def on_headers_complete(self) -> None:
            self._in_headers = False
            self._disarm()
            super().on_headers_complete()
            self._arm(limits.body_timeout_s, "its body")

        def on_message_complete(self) -> None:
            self._disarm()
            super().on_message_complete()
            self._header_bytes, self._in_headers = 0, True  # what comes next is the next request's headers

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _arm(self, seconds: float, what: str) -> None:
            self._disarm()
            self._deadline = self.loop.call_later(seconds, self._timed_out, seconds, what)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _timed_out(self, seconds: float, what: str) -> None:
            self._deadline = None
            if self.transport.is_closing():
                return
            if self.cycle is not None and not self.cycle.response_complete:
                if self.cycle.response_started:  # the application answers already: only the connection ends
                    self.transport.close()
                    return
                self.cycle.disconnected = True  # the application reading the body sees the client gone
                self.cycle.message_event.set()
            self._refuse(408, "request-timeout", f"A request must send {what} within {seconds:g} s.")

        def _refuse(self, status: int, kind: str, detail: str) -> None:
            """Answer problem+json and close: written here, as no application runs for the request. The close
            lingers (nginx's lingering_close): the answer is followed by a FIN, what the client still sends is
            read and dropped for ``_LINGER_S`` (at most ``_LINGER_BYTES``), then the socket is closed; closed at
            once with unread bytes, the kernel would send a reset that can destroy the answer before the client
            reads it."""
            self._disarm()
            self._refused = True
            phrase = HTTPStatus(status).phrase
            body = json.dumps({"type": PROBLEM_TYPE_BASE + kind, "title": phrase, "status": status, "detail": detail,
                               "instance": self.scope.get("path", "") if self.scope else ""}).encode()
            self.transport.write(b"HTTP/1.1 %d %s\r\ncontent-type: %s\r\ncontent-length: %d\r\n"
                                 b"connection: close\r\n\r\n%s" % (status, phrase.encode(), PROBLEM_MEDIA_TYPE.encode(),
                                                                   len(body), body))
            if self.transport.can_write_eof():
                self.transport.write_eof()
                self.loop.call_later(_LINGER_S, self.transport.close)
            else:
                self.transport.close()

    return LimitedHttpProtocol


def server_config(app: Any, host: str, port: int, limits: HttpLimits, **options: Any) -> uvicorn.Config:
    """uvicorn's configuration of ``app`` on ``host:port`` with the httptools protocol bounded by ``limits``."""
    return uvicorn.Config(app, host=host, port=port, http=limited_protocol(limits), **options)


def serve(app: Any, host: str, port: int, limits: HttpLimits, **options: Any) -> None:
    """Serve ``app`` until the process is told to stop (uvicorn's ``run`` with the bounded protocol)."""
    uvicorn.Server(server_config(app, host, port, limits, **options)).run()
