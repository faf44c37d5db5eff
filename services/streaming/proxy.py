"""Rerun's gRPC proxy as a child process, bound to one address (127.0.0.1 by default).

The SDK's own ``serve_grpc`` always listens on every interface; the ``rerun`` CLI
takes ``--bind``, so the embedded default runs that. Viewers join with
``rerun --connect rerun+http://HOST:PORT/proxy``; the SDK logs to the same URL. With a web port the
same process also serves Rerun's web viewer (it ships in the rerun-sdk wheel) over HTTP on the same
address, so an operator needs only a browser: ``web_viewer_url`` opens it on the proxy.
"""

from __future__ import annotations

import os
import socket
import subprocess
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

import rerun_cli

from services.errors import InputError


def proxy_url(host: str, port: int) -> str:
    """The URL loggers and viewers use to reach a proxy."""
    return f"rerun+http://{host}:{port}/proxy"


def web_viewer_url(host: str, web_port: int, grpc_port: int) -> str:
    """The address that opens Rerun's web viewer, served on ``web_port``, on the proxy at ``grpc_port``."""
    return f"http://{host}:{web_port}/?url={quote(proxy_url(host, grpc_port), safe='')}"


def rerun_executable() -> str:
    """The ``rerun`` binary shipped in the rerun-sdk wheel (``RERUN_CLI_PATH`` overrides it).

    Run directly rather than through ``python -m rerun_cli``, whose wrapper process
    would leave the binary running when it is terminated.
    """
    return os.environ.get("RERUN_CLI_PATH") or str(Path(rerun_cli.__file__).with_name("rerun"))


class RerunProxy:
    """A running ``rerun --serve-grpc`` on ``host:port`` (``--serve-web`` when ``web_port`` is given: the web
    viewer too, on ``host:web_port``); a context manager that stops it on exit."""

    def __init__(self, host: str = "127.0.0.1", port: int = 9876, memory_limit: str = "1GiB",
                 start_timeout_s: float = 15.0, web_port: int | None = None) -> None:
        self.host, self.port, self.web_port = host, port, web_port
        self.url = proxy_url(host, port)
        self.viewer_url = None if web_port is None else web_viewer_url(host, web_port, port)
        for busy, setting in ((port, "THERMOFIELD_RERUN_PORT"), (web_port, "THERMOFIELD_RERUN_WEB_PORT")):
            if busy is not None and accepts_connections(host, busy):
                raise InputError(f"Rerun port {busy} on {host} is already in use; choose another ({setting})")
        serve = ["--serve-grpc"] if web_port is None else ["--serve-web", "--web-viewer-port", str(web_port)]
        self._log = tempfile.TemporaryFile()
        self._process = subprocess.Popen(
            [rerun_executable(), *serve, "--bind", host, "--port", str(port),
             "--server-memory-limit", memory_limit],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=self._log,
            env={"RUST_LOG": "warn", **os.environ},  # its log is kept only to explain a failed start
        )
        deadline = time.monotonic() + start_timeout_s
        while not all(accepts_connections(host, listening) for listening in (port, web_port) if listening is not None):
            if self._process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                self._log.seek(0)
                error = self._log.read().decode(errors="replace").strip().splitlines()
                reason = error[-1] if error else "timeout"
                raise RuntimeError(f"the Rerun proxy did not start on {host}:{port}: {reason}")
            time.sleep(0.05)

    def __enter__(self) -> RerunProxy:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._process.poll() is None

    def stop(self) -> None:
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._log.close()


def accepts_connections(host: str, port: int) -> bool:
    """Whether something listens on ``host:port`` (a 0.2 s TCP probe)."""
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False
