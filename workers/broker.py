"""The Dramatiq broker: RabbitMQ when scaled out, an in-memory broker for the embedded in-process worker."""

from __future__ import annotations

import importlib
import logging

import dramatiq
from dramatiq.brokers.rabbitmq import RabbitmqBroker
from dramatiq.brokers.stub import StubBroker

from services.settings import Settings
from workers.heartbeat import Heartbeat
from workers.middleware import ComputeThreads, JobBookkeeping


class _ResultsGoToTheJobsTable(logging.Filter):
    """Drops Dramatiq's warning that an actor's return value is discarded: JobBookkeeping stores it as the
    job's result."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Results middleware" not in record.getMessage()


def setup_broker(settings: Settings) -> dramatiq.Broker:
    """Build the broker for ``settings``, make it the global one and declare every actor on it."""
    broker: dramatiq.Broker
    if settings.broker_url:
        broker = RabbitmqBroker(url=settings.broker_url)
    else:
        broker = StubBroker()
    broker.add_middleware(ComputeThreads(settings.compute_threads))
    broker.add_middleware(JobBookkeeping())
    if settings.broker_url:
        broker.add_middleware(Heartbeat(settings.job_queue))  # read by `thermofield worker --check`
    else:
        broker.emit_after("process_boot")  # the dramatiq CLI does this for its processes; it starts TimeLimit's timer
    dramatiq.set_broker(broker)
    logging.getLogger("dramatiq.worker.WorkerThread").addFilter(_ResultsGoToTheJobsTable())
    actors = importlib.import_module("workers.actors")
    for actor in actors.ACTORS.values():
        actor.broker, actor.queue_name = broker, settings.job_queue
        broker.declare_actor(actor)
    return broker


def send_job(kind: str, job_id: str) -> None:
    """Queue job ``job_id`` for the actor named ``kind`` on the global broker."""
    dramatiq.get_broker().get_actor(kind).send(job_id)
