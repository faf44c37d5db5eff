"""Following the workers' job states over the machine's real Mosquitto (the scaled-out API's OPC UA feed)."""

import time
import uuid

import paho.mqtt.client as mqtt

from services.events.job_states import JobStateSubscriber
from services.events.mqtt import EventPublisher, job_topic


def _wait_for(condition, timeout_s: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.05)
    return condition()


def _state(job_id: str, status: str, attempts: int = 1) -> dict:
    return {"job_id": job_id, "kind": "scan", "status": status, "stage": status, "fraction": 0.0,
            "attempts": attempts, "scan_id": f"scan-of-{job_id}", "error": None}


def test_every_state_is_heard_once_in_order_and_bad_payloads_are_ignored():
    prefix = f"test-{uuid.uuid4().hex[:8]}/station1"
    heard = []
    with JobStateSubscriber("127.0.0.1", 1883, prefix, heard.append) as subscriber:
        probe = mqtt.Client(mqtt.CallbackAPIVersion.VERSION2)
        probe.connect("127.0.0.1", 1883)
        probe.loop_start()
        assert subscriber.subscribed.wait(20)  # a state published before the subscription would be missed
        publisher = EventPublisher("127.0.0.1", 1883, prefix)
        states = [_state("j1", "queued", 0), _state("j1", "running"), _state("j1", "succeeded")]
        for state in states:
            publisher.publish(job_topic(prefix, "j1"), state)
        publisher.publish(job_topic(prefix, "j1"), states[-1])  # a duplicate, as QoS 1 may deliver
        probe.publish(job_topic(prefix, "j2"), b"not json", qos=1).wait_for_publish(5)
        publisher.publish(job_topic(prefix, "j2"), _state("j2", "failed"))
        publisher.publish(f"{prefix}/scans/other", _state("j3", "succeeded"))  # not a job topic
        # MQTT keeps the order of one topic's messages: once each job's marker, published last on its topic,
        # is heard, anything else published on it (a duplicate let through) would have been heard before.
        for job in ("j1", "j2"):
            publisher.publish(job_topic(prefix, job), _state(job, "marker"))
        assert _wait_for(lambda: {"j1", "j2"} <= {state["job_id"] for state in heard if state["status"] == "marker"})
        heard = [state for state in heard if state["status"] != "marker"]
        publisher.close()
        probe.loop_stop()
        probe.disconnect()
    # MQTT keeps the order of one topic's messages, not across topics: each job's states in order
    by_job = {job: [s["status"] for s in heard if s["job_id"] == job] for job in ("j1", "j2", "j3")}
    assert by_job == {"j1": ["queued", "running", "succeeded"], "j2": ["failed"], "j3": []}
    assert len(heard) == 4
