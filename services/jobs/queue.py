"""The job queue as the API sees it: messages to actors by name, without importing the actors.

A job is a row in the jobs table (:mod:`services.jobs.tracker`) plus one Dramatiq message carrying its
id to the actor named after its kind. Enqueueing needs only the broker's transport, so the API process
never loads the workers' science.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import dramatiq
from dramatiq.brokers.rabbitmq import RabbitmqBroker
from dramatiq.brokers.stub import StubBroker
from dramatiq.common import dq_name, xq_name

from services.settings import Settings


def job_broker(settings: Settings) -> dramatiq.Broker:
    """The transport: RabbitMQ when ``settings.broker_url`` is set, else an in-memory broker for the
    embedded in-process worker. Made the global broker. RabbitMQ confirms every message it takes
    (publisher confirms), so a message sent as the broker goes down raises instead of vanishing."""
    broker = RabbitmqBroker(url=settings.broker_url, confirm_delivery=True) if settings.broker_url else StubBroker()
    dramatiq.set_broker(broker)
    return broker


class JobQueue:
    """Sends job ids to actors by name on one queue of ``broker``, every message from one thread.

    Dramatiq's RabbitMQ broker opens a connection for each thread that sends and keeps it
    for the life of the broker. The API sends from the threads of its thread pool, which
    anyio retires after 10 s idle and replaces with new ones, so each send from a fresh
    thread would leave one more open connection behind (the API's file descriptors grew
    33 -> 73 in the soak, docs/reliability.md). Sending from one thread of this queue keeps
    it to one connection per process.
    """

    def __init__(self, broker: dramatiq.Broker, queue_name: str) -> None:
        self.broker, self.queue_name = broker, queue_name
        self._sender = ThreadPoolExecutor(max_workers=1, thread_name_prefix="job-queue")
        self._sender.submit(broker.declare_queue, queue_name).result()

    def send(self, kind: str, job_id: str) -> dramatiq.Message:
        """Queue job ``job_id`` for the actor named ``kind`` (blocks until the broker has taken it)."""
        message = dramatiq.Message(queue_name=self.queue_name, actor_name=kind, args=(job_id,), kwargs={},
                                   options={})
        return self._sender.submit(self.broker.enqueue, message).result()


def delete_job_queues(broker_url: str, queue_name: str) -> None:
    """Delete the job queue ``queue_name`` on the RabbitMQ at ``broker_url``, with the delay and dead-letter
    queues Dramatiq declares beside it (for throwaway deployments: the tests' and benchmarks')."""
    import pika

    connection = pika.BlockingConnection(pika.URLParameters(broker_url))
    try:
        channel = connection.channel()
        for name in (queue_name, dq_name(queue_name), xq_name(queue_name)):
            channel.queue_delete(name)
    finally:
        connection.close()
