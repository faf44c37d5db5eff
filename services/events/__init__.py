"""Job and scan state published to MQTT for plant systems (MES) that subscribe instead of polling."""

from services.events.mqtt import EventPublisher, job_topic, scan_topic

__all__ = ["EventPublisher", "job_topic", "scan_topic"]
