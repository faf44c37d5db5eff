"""Worker processes' heartbeats, what the worker container's healthcheck reads.

Its own module, apart from the other middleware: the healthcheck (``thermofield worker --check``)
runs every few seconds and must not pay for importing OpenCV and numba.
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path

from dramatiq.middleware import Middleware


HEARTBEAT_INTERVAL_S = 5.0


def heartbeat_dir() -> Path:
    """Where worker processes leave their heartbeat files (one per process, touched every few seconds)."""
    return Path(tempfile.gettempdir()) / "thermofield-heartbeats"


class Heartbeat(Middleware):
    """Touches ``heartbeat_dir()/<queue>-<pid>`` every few seconds while the worker process runs.

    Dramatiq has no health endpoint; a fresh file per process is what a container's
    healthcheck (``thermofield worker --check``) reads: every process booted, consumes
    and has not hung.
    """

    def __init__(self, queue: str) -> None:
        self.queue = queue
        self._stop = threading.Event()

    @property
    def path(self) -> Path:
        return heartbeat_dir() / f"{self.queue}-{os.getpid()}"

    def after_worker_boot(self, broker, worker) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.touch()  # alive from the moment it booted
        threading.Thread(target=self._beat, name="heartbeat", daemon=True).start()

    def before_worker_shutdown(self, broker, worker) -> None:
        self._stop.set()
        self.path.unlink(missing_ok=True)

    def _beat(self) -> None:
        while not self._stop.is_set():
            self.path.touch()
            self._stop.wait(HEARTBEAT_INTERVAL_S)


def live_worker_processes(queue: str, max_age_s: float = 6 * HEARTBEAT_INTERVAL_S) -> int:
    """How many worker processes of ``queue`` left a heartbeat within ``max_age_s``."""
    now, live = time.time(), 0
    for path in heartbeat_dir().glob(f"{queue}-*"):
        try:
            live += now - path.stat().st_mtime <= max_age_s
        except FileNotFoundError:
            pass  # its process shut down between the listing and the look
    return live
