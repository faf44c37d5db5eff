"""Rerun recordings of scans: one ``.rrd`` per scan (an artifact) and the live station view.

The per-scan recording has the scan id as its recording id, so the ``.rrd`` kept
with a scan opens on its own in the viewer. The live view is one long recording per
station, ``station-<name>``, streamed to a Rerun gRPC proxy; each field lands at the
next step of its ``scan`` timeline, so a viewer following the latest time shows
every new field as it arrives.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import rerun as rr

from services.formats.rig import Rig
from services.streaming.field import log_field

APPLICATION_ID = "thermofield"


def _set_scan_time(recording: rr.RecordingStream, scan_number: int, captured_at: float | None) -> None:
    recording.set_time("scan", sequence=scan_number)
    recording.set_time("capture_time", timestamp=time.time() if captured_at is None else captured_at)


def scan_recording(
    scan_id: str,
    field: dict[str, np.ndarray],
    rig: Rig,
    thermal_image: np.ndarray | None = None,
    captured_at: float | None = None,
) -> bytes:
    """The ``.rrd`` bytes of one scan's field, rig and thermal frame (see :func:`log_field`).

    ``captured_at`` (seconds since the epoch) stamps the ``capture_time`` timeline;
    default now.
    """
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=scan_id)
    memory = recording.memory_recording()
    recording.send_recording_name(f"scan {scan_id}")
    _set_scan_time(recording, 0, captured_at)
    log_field(recording, field, rig, thermal_image)
    recording.flush()
    data = memory.drain_as_bytes()
    recording.disconnect()
    return data


class StationView:
    """The live view of a station: every new field streamed to the Rerun proxy at ``url``.

    ``url`` is the proxy's address, ``rerun+http://HOST:PORT/proxy``. Logging never
    blocks a scan: Rerun buffers and sends in the background, and a proxy that is down
    only loses the live picture (each scan's ``.rrd`` is kept regardless).
    """

    def __init__(self, url: str, station: str) -> None:
        self.url = url
        self._recording = rr.RecordingStream(APPLICATION_ID, recording_id=f"station-{station}")
        self._recording.send_recording_name(f"station {station} (live)")
        self._recording.connect_grpc(url)
        self._scans = 0
        self._lock = threading.Lock()

    def publish(self, field: dict[str, np.ndarray], rig: Rig, thermal_image: np.ndarray | None = None,
                captured_at: float | None = None) -> int:
        """Show a new field; returns its step on the ``scan`` timeline."""
        with self._lock:
            self._scans += 1
            _set_scan_time(self._recording, self._scans, captured_at)
            log_field(self._recording, field, rig, thermal_image)
            return self._scans

    def close(self) -> None:
        self._recording.flush()
        self._recording.disconnect()
