"""The HTTP server's bounds (api/server.py), on a real uvicorn on a free port, spoken to over raw sockets:
headers over the size limit get 431, headers or a body that do not arrive in time 408, each closing the
connection; requests within the bounds, kept alive, are served."""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator

import pytest
from fastapi import FastAPI, Request

from api.server import HttpLimits, server_config

LIMITS = HttpLimits(max_header_bytes=4096, header_timeout_s=0.5, body_timeout_s=0.5)


@pytest.fixture
def port() -> Iterator[int]:
    import uvicorn

    app = FastAPI()

    @app.get("/ping")
    def ping() -> dict[str, str]:
        return {"status": "ok"}

    @app.post("/echo")
    async def echo(request: Request) -> dict[str, int]:
        return {"bytes": len(await request.body())}

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    server = uvicorn.Server(server_config(app, "127.0.0.1", free, LIMITS, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    yield free
    server.should_exit = True
    thread.join(timeout=10)


def _answer(connection: socket.socket) -> tuple[int, dict, bytes, bool]:
    """Status, headers and body of one response, and whether the server closed the connection after it."""
    connection.settimeout(10)  # far beyond the bounds: a server that never answers fails here
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = connection.recv(65536)
        assert chunk, f"closed without an answer after {data!r}"
        data += chunk
    head, body = data.split(b"\r\n\r\n", 1)
    lines = head.decode().split("\r\n")
    headers = {name.lower(): value.strip() for name, value in (line.split(":", 1) for line in lines[1:])}
    while len(body) < int(headers.get("content-length", 0)):
        body += connection.recv(65536)
    try:
        connection.settimeout(2)
        closed = connection.recv(1) == b""
    except TimeoutError:
        closed = False
    return int(lines[0].split()[1]), headers, body, closed


def test_requests_within_the_bounds_are_served_on_a_kept_alive_connection(port):
    with socket.create_connection(("127.0.0.1", port)) as connection:
        for _ in range(2):
            connection.sendall(b"GET /ping HTTP/1.1\r\nHost: api\r\nX-Padding: " + b"a" * 3000 + b"\r\n\r\n")
            status, _, body, closed = _answer(connection)
            assert status == 200 and json.loads(body) == {"status": "ok"} and not closed
        connection.sendall(b"POST /echo HTTP/1.1\r\nHost: api\r\nContent-Length: 100000\r\n\r\n" + b"x" * 100000)
        status, _, body, _ = _answer(connection)
        assert status == 200 and json.loads(body) == {"bytes": 100000}


@pytest.mark.parametrize("piece", [8 << 10, 512 << 10])
def test_headers_over_the_limit_are_431_and_close_the_connection(port, piece):
    """Up to 768 kB of headers never finished: within what the server reads and drops after refusing (1 MiB),
    so that the answer arrives before the connection closes; beyond it the server cuts the connection."""
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(b"GET /ping HTTP/1.1\r\nHost: api\r\n")
        try:
            for _ in range(max(1, (768 << 10) // piece)):
                connection.sendall(b"X-Filler: " + b"a" * piece + b"\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server closed the connection mid-way, as it should
        status, headers, body, closed = _answer(connection)
    assert status == 431 and headers["content-type"] == "application/problem+json" and closed
    assert json.loads(body)["type"].endswith("/request-header-fields-too-large") and "4096" in json.loads(body)["detail"]


@pytest.mark.parametrize("sent", [b"", b"GET /ping HTTP/1.1\r\nHost: ap"])
def test_headers_that_do_not_arrive_in_time_are_408(port, sent):
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(sent)
        status, headers, body, closed = _answer(connection)
    assert status == 408 and headers["content-type"] == "application/problem+json" and closed
    assert "headers within 0.5 s" in json.loads(body)["detail"]


def test_a_body_that_does_not_arrive_in_time_is_408(port):
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(b"POST /echo HTTP/1.1\r\nHost: api\r\nContent-Length: 1000\r\n\r\n" + b"x" * 10)
        status, _, body, closed = _answer(connection)
    assert status == 408 and closed and "body within 0.5 s" in json.loads(body)["detail"]


def test_a_slow_client_dripping_headers_is_cut_at_the_time_limit(port):
    """Slowloris: a byte of header every 0.1 s keeps the connection busy but never finishes in time."""
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(b"GET /ping HTTP/1.1\r\n")
        try:
            for _ in range(40):  # 4 s of dripping, against a 0.5 s bound
                connection.sendall(b"X")
                time.sleep(0.1)  # the test: the slow client's pace
        except (BrokenPipeError, ConnectionResetError):
            pass
        status, _, _, closed = _answer(connection)
    assert status == 408 and closed


def test_the_next_requests_headers_on_a_kept_alive_connection_are_bounded_too(port):
    with socket.create_connection(("127.0.0.1", port)) as connection:
        connection.sendall(b"GET /ping HTTP/1.1\r\nHost: api\r\n\r\nGET /ping HTTP/1.1\r\nHost: api\r\n")
        status, _, _, closed = _answer(connection)
        assert status == 200 and not closed
        try:
            for _ in range(64):  # 512 kB of the second request's headers
                connection.sendall(b"X-Filler: " + b"a" * 8192 + b"\r\n")
        except (BrokenPipeError, ConnectionResetError):
            pass
        status, _, _, closed = _answer(connection)
    assert status == 431 and closed
