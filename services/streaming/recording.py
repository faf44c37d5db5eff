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
from urllib.parse import urlsplit

import rerun as rr

from services.streaming.field import FieldScene, log_field
from services.streaming.proxy import accepts_connections

APPLICATION_ID = "thermofield"


def _set_scan_time(recording: rr.RecordingStream, scan_number: int, captured_at: float | None) -> None:
    recording.set_time("scan", sequence=scan_number)
    recording.set_time("capture_time", timestamp=time.time() if captured_at is None else captured_at)


def scan_recording(scan_id: str, scene: FieldScene, captured_at: float | None = None) -> bytes:
    """The ``.rrd`` bytes of one scan's field, rig and thermal frame (see :func:`field_scene`).

    ``captured_at`` (seconds since the epoch) stamps the ``capture_time`` timeline;
    default now.

    Rerun never drops a Python recording stream by itself, only disconnects it: each
    would keep its two threads and their buffers for the life of the process
    (rerun-io/rerun#2116; a worker grew by a thread and about 3 MB per scan in the
    soak, docs/reliability.md). Once the stream is released, the orphaned streams are
    cleaned up, as ``rr.init`` does.
    """
    recording = rr.RecordingStream(APPLICATION_ID, recording_id=scan_id)
    memory = recording.memory_recording()
    recording.send_recording_name(f"scan {scan_id}")
    _set_scan_time(recording, 0, captured_at)
    log_field(recording, scene)
    recording.flush()
    data = memory.drain_as_bytes()
    recording.disconnect()
    del recording, memory
    rr.bindings.flush_and_cleanup_orphaned_recordings()
    return data


class StationView:
    """The live view of a station: every new field streamed to the Rerun proxy at ``url``.

    ``url`` is the proxy's address, ``rerun+http://HOST:PORT/proxy``. The view never
    holds up a scan: connecting to a proxy that is down would block for seconds inside
    Rerun, so the proxy is probed first (0.2 s) and the view connects on the first
    publish that finds it up. Once connected, Rerun buffers and sends in the
    background. A proxy that is down costs only the live picture; each scan's ``.rrd``
    is kept regardless.
    """

    def __init__(self, url: str, station: str) -> None:
        address = urlsplit(url.removeprefix("rerun+"))
        if address.hostname is None or address.port is None:
            raise ValueError(f"The Rerun proxy URL must look like rerun+http://HOST:PORT/proxy; got {url!r}.")
        self.url = url
        self.station = station
        self._address = (address.hostname, address.port)
        self._recording: rr.RecordingStream | None = None
        self._scans = 0
        self._lock = threading.Lock()

    def _connected(self) -> rr.RecordingStream | None:
        if self._recording is None and accepts_connections(*self._address):
            recording = rr.RecordingStream(APPLICATION_ID, recording_id=f"station-{self.station}")
            recording.connect_grpc(self.url)
            recording.send_recording_name(f"station {self.station} (live)")
            self._recording = recording
        return self._recording

    def publish(self, scene: FieldScene, captured_at: float | None = None) -> int | None:
        """Show a new field; returns its step on the ``scan`` timeline, None when the proxy is unreachable."""
        with self._lock:
            self._scans += 1
            recording = self._connected()
            if recording is None:
                return None
            _set_scan_time(recording, self._scans, captured_at)
            log_field(recording, scene)
            return self._scans

    def close(self) -> None:
        """Send what is buffered (waiting at most a few seconds) and disconnect."""
        with self._lock:
            if self._recording is not None:
                try:
                    self._recording.flush(timeout_sec=5.0)
                except RuntimeError:
                    pass  # the proxy went away: the live picture is lost, nothing else
                self._recording.disconnect()
                self._recording = None
