"""Publishing job and scan states as JSON messages over MQTT (paho-mqtt 2).

Topic tree (``site`` and ``station`` from the settings)::

    <site>/<station>/state             the station's latest change (a scan's or job's state), retained
    <site>/<station>/jobs/<job id>     {"job_id", "kind", "status", "stage", "fraction", "attempts", "error", ...}
    <site>/<station>/scans/<scan id>   {"scan_id", "job_id", "status", "stage", "fraction", "summary", ...}

Messages are QoS 1. Only the station's state is retained, so a subscriber that
connects later gets the station's latest state at once, and the broker keeps one
message per station instead of one per job and scan forever; per-id topics are
live updates (the API has every job's and scan's state).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from typing import Any

import paho.mqtt.client as mqtt

logger = logging.getLogger(__name__)
_FLUSH_TIMEOUT_S = 5.0


def job_topic(prefix: str, job_id: str) -> str:
    return f"{prefix}/jobs/{job_id}"


def scan_topic(prefix: str, scan_id: str) -> str:
    return f"{prefix}/scans/{scan_id}"


def station_topic(prefix: str) -> str:
    return f"{prefix}/state"


class EventPublisher:
    """A connected MQTT client that publishes JSON states under ``prefix``.

    A broker outage never fails a job: publishing logs a warning and the job's
    state stays in the database, which remains the source of truth.
    """

    def __init__(self, host: str, port: int, prefix: str, client_id: str = "") -> None:
        self.prefix = prefix
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self._client.reconnect_delay_set(min_delay=1, max_delay=10)
        self._lock = threading.Lock()
        self._last: mqtt.MQTTMessageInfo | None = None
        self._client.connect_async(host, port, keepalive=30)
        self._client.loop_start()

    def publish(self, topic: str, state: dict[str, Any], retain: bool = False) -> None:
        """Queue a QoS 1 message; the client's network thread delivers it (and re-sends it after a
        reconnection), so a job never waits for the broker."""
        payload = json.dumps(state, default=str, separators=(",", ":"))
        with self._lock:
            info = self._client.publish(topic, payload, qos=1, retain=retain)
        if info.rc not in (mqtt.MQTT_ERR_SUCCESS, mqtt.MQTT_ERR_NO_CONN):
            logger.warning("MQTT publish to %s failed: %s", topic, mqtt.error_string(info.rc))
        self._last = info

    def close(self) -> None:
        """Deliver what is queued (a few seconds at most), then disconnect."""
        deadline = time.monotonic() + _FLUSH_TIMEOUT_S
        while self._last is not None and not self._client.is_connected() and time.monotonic() < deadline:
            time.sleep(0.05)
        if self._last is not None and self._client.is_connected():
            try:
                self._last.wait_for_publish(timeout=max(deadline - time.monotonic(), 0.1))
            except (RuntimeError, ValueError) as error:
                logger.warning("MQTT messages still queued at close: %s", error)
        self._client.loop_stop()
        self._client.disconnect()
