"""Publishing job and scan states as retained JSON messages over MQTT (paho-mqtt 2).

Topic tree (``site`` and ``station`` from the settings)::

    <site>/<station>/jobs/<job id>     {"job_id", "kind", "status", "stage", "fraction", "attempts", "error", ...}
    <site>/<station>/scans/<scan id>   {"scan_id", "job_id", "status", "stage", "fraction", "summary", ...}

Messages are QoS 1 and retained, so a subscriber that connects later receives the
last state of every job and scan at once.
"""

from __future__ import annotations

import json
import logging
import threading
from typing import Any

import paho.mqtt.client as mqtt

logger = logging.getLogger(__name__)
_PUBLISH_TIMEOUT_S = 5.0


def job_topic(prefix: str, job_id: str) -> str:
    return f"{prefix}/jobs/{job_id}"


def scan_topic(prefix: str, scan_id: str) -> str:
    return f"{prefix}/scans/{scan_id}"


class EventPublisher:
    """A connected MQTT client that publishes retained JSON states under ``prefix``.

    A broker outage never fails a job: publishing logs a warning and the job's
    state stays in the database, which remains the source of truth.
    """

    def __init__(self, host: str, port: int, prefix: str, client_id: str = "") -> None:
        self.prefix = prefix
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self._client.reconnect_delay_set(min_delay=1, max_delay=10)
        self._lock = threading.Lock()
        self._client.connect_async(host, port, keepalive=30)
        self._client.loop_start()

    def publish(self, topic: str, state: dict[str, Any]) -> None:
        payload = json.dumps(state, default=str, separators=(",", ":"))
        with self._lock:
            info = self._client.publish(topic, payload, qos=1, retain=True)
        try:
            info.wait_for_publish(timeout=_PUBLISH_TIMEOUT_S)
        except (RuntimeError, ValueError) as error:
            logger.warning("MQTT publish to %s failed: %s", topic, error)

    def close(self) -> None:
        self._client.loop_stop()
        self._client.disconnect()
