"""The transactional outbox on SQLite and PostgreSQL: pending jobs are sent once each, even by two senders
at once (two API processes); a broker that cannot be reached leaves them pending, never lost."""

import threading
import uuid

import dramatiq
import pika
import pytest
from dramatiq.brokers.rabbitmq import RabbitmqBroker
from dramatiq.brokers.stub import StubBroker

from services.db.engine import make_sessions
from services.db.models import Job
from services.jobs.outbox import Outbox
from services.jobs.queue import JobQueue
from services.jobs.tracker import JobTracker


def _pending_jobs(sessions, count: int) -> list[str]:
    tracker = JobTracker(sessions)
    with sessions.begin() as session:
        return [tracker.create(session, "scan", {"index": i}).id for i in range(count)]


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _sent(queue: JobQueue) -> list[str]:
    import json

    return [json.loads(data)["args"][0] for data in queue.broker.queues[queue.queue_name].queue]


def test_two_senders_at_once_send_each_pending_job_once(engine):
    sessions = make_sessions(engine)
    ids = _pending_jobs(sessions, 40)
    queue = JobQueue(StubBroker(), "outbox-test")
    outboxes = [Outbox(sessions, queue), Outbox(sessions, queue)]
    barrier = threading.Barrier(3)

    def drain(outbox: Outbox, one_by_one: bool) -> None:
        barrier.wait()
        if one_by_one:  # as requests do, each sending its own job
            for job_id in ids:
                outbox.send(job_id)
        else:  # as the outbox thread does
            while outbox.send_pending(batch=5):
                pass

    threads = [threading.Thread(target=drain, args=(outbox, i == 1)) for i, outbox in enumerate(outboxes)]
    for thread in threads:
        thread.start()
    barrier.wait()
    for thread in threads:
        thread.join(60)
    assert sorted(_sent(queue)) == sorted(ids)  # every job once, none twice
    assert outboxes[0].pending() == 0


def test_a_refusing_broker_leaves_the_jobs_pending_and_the_thread_sends_them_later(engine):
    sessions = make_sessions(engine)
    ids = _pending_jobs(sessions, 3)
    port = _free_port()  # RabbitMQ's client against a port where no broker listens
    down = Outbox(sessions, JobQueue(RabbitmqBroker(url=f"amqp://guest:guest@127.0.0.1:{port}",
                                                    confirm_delivery=True), "outbox-test"))
    assert down.send(ids[0]) is False
    with pytest.raises(dramatiq.errors.ConnectionClosed):
        down.send_pending()
    assert down.pending() == 3
    with sessions() as session:
        assert all(session.get(Job, job_id).dispatched_at is None for job_id in ids)
    queue = JobQueue(StubBroker(), "outbox-test")
    with Outbox(sessions, queue, poll_s=0.05) as outbox:  # the broker is back: its thread sends them, in order
        for _ in range(100):
            if outbox.pending() == 0:
                break
            threading.Event().wait(0.05)
    assert _sent(queue) == ids


@pytest.mark.postgres  # the machine's RabbitMQ
def test_the_queue_sends_over_one_connection_whichever_thread_calls_it():
    """The API sends from its thread pool's threads, which come and go; Dramatiq's broker would open a
    connection per thread and keep each (the API's descriptors grew in the soak): one connection for all."""
    url, queue_name = "amqp://guest:guest@127.0.0.1:5672", f"tf-queue-test-{uuid.uuid4().hex[:8]}"
    broker = RabbitmqBroker(url=url, confirm_delivery=True)
    queue = JobQueue(broker, queue_name)
    connection = pika.BlockingConnection(pika.URLParameters(url))
    try:
        for index in range(4):  # each from a thread that then ends, as retired pool threads do
            thread = threading.Thread(target=queue.send, args=("scan", f"job-{index}"))
            thread.start()
            thread.join(30)
        assert len(broker.connections) == 1
        assert connection.channel().queue_declare(queue_name, passive=True).method.message_count == 4
    finally:
        broker.close()
        channel = connection.channel()
        for name in (queue_name, f"{queue_name}.DQ", f"{queue_name}.XQ"):
            channel.queue_delete(name)
        connection.close()
