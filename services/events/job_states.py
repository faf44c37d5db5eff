"""Hearing job states over MQTT: how a process that runs no jobs (the scaled-out API) follows the workers'."""

from __future__ import annotations

import json
import logging
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import paho.mqtt.client as mqtt

from services.events.mqtt import job_topic

logger = logging.getLogger(__name__)
_REMEMBERED_STATES = 4096  # QoS 1 may deliver a message twice: recent states are recognised and dropped


class JobStateSubscriber:
    """Calls ``on_state`` with every job state the workers publish under ``prefix`` (started as a context manager).

    Parameters
    ----------
    host, port : str, int
        The MQTT broker.
    prefix : str
        The station's topic prefix (``<site>/<station>``); ``<prefix>/jobs/+`` is followed.
    on_state : callable
        Called on the client's network thread with each state (the payload of ``job_topic``), once per job,
        status and attempt: a redelivered duplicate is dropped. It must not block.

    Notes
    -----
    The subscription is QoS 1 and renewed on every reconnection. States published while the broker or this
    process was away are not heard (the broker keeps no per-job messages, see ``services.events.mqtt``): the
    database stays the source of truth.
    """

    def __init__(self, host: str, port: int, prefix: str, on_state: Callable[[dict[str, Any]], None],
                 client_id: str = "") -> None:
        self.topic = job_topic(prefix, "+")
        self._on_state = on_state
        self.subscribed = threading.Event()  # set once the broker has acknowledged the subscription
        self._seen: OrderedDict[tuple, None] = OrderedDict()
        self._client = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2, client_id=client_id)
        self._client.reconnect_delay_set(min_delay=1, max_delay=10)
        self._client.on_connect = self._subscribe
        self._client.on_subscribe = lambda *_: self.subscribed.set()
        self._client.on_message = self._receive
        self._host, self._port = host, port

    def __enter__(self) -> JobStateSubscriber:
        self._client.connect_async(self._host, self._port, keepalive=30)
        self._client.loop_start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._client.disconnect()
        self._client.loop_stop()

    def _subscribe(self, client, userdata, flags, reason_code, properties) -> None:
        client.subscribe(self.topic, qos=1)

    def _receive(self, client, userdata, message: mqtt.MQTTMessage) -> None:
        try:
            state = json.loads(message.payload)
            key = (state["job_id"], state["status"], state.get("attempts"), state.get("stage"), state.get("fraction"))
        except (ValueError, TypeError, KeyError):
            logger.warning("MQTT: %s carried no job state; ignored", message.topic)
            return
        if key in self._seen:
            return
        self._seen[key] = None
        if len(self._seen) > _REMEMBERED_STATES:
            self._seen.popitem(last=False)
        try:
            self._on_state(state)
        except Exception:
            logger.exception("a job-state listener failed")
