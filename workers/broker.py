"""The workers' broker: the job transport (:func:`services.jobs.queue.job_broker`) with the service
middleware and every actor declared on the job queue."""

from __future__ import annotations

import logging

import dramatiq
from dramatiq.middleware import GroupCallbacks

from services.jobs.barrier import DatabaseBarrierBackend
from services.jobs.queue import job_broker
from services.runtime import current_runtime
from services.settings import Settings
from workers.heartbeat import Heartbeat
from workers.middleware import ComputeThreads, JobBookkeeping, WarmUp


class _ResultsGoToTheJobsTable(logging.Filter):
    """Drops Dramatiq's warning that an actor's return value is discarded: JobBookkeeping stores it as the
    job's result."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "Results middleware" not in record.getMessage()


def setup_broker(settings: Settings) -> dramatiq.Broker:
    """Build the broker for ``settings``, make it the global one and declare every actor on it."""
    from workers.actors import ACTORS

    broker = job_broker(settings)
    broker.add_middleware(ComputeThreads(settings.compute_threads))
    # Dramatiq runs the after_* hooks in the reverse order of the list (Broker.emit_after): with the group callbacks
    # before the bookkeeping, a group's last message has its job recorded before its completion callback is sent
    broker.add_middleware(GroupCallbacks(DatabaseBarrierBackend(lambda: current_runtime().sessions)))
    broker.add_middleware(JobBookkeeping())
    if settings.warm_up:
        broker.add_middleware(WarmUp())
    if settings.broker_url:
        broker.add_middleware(Heartbeat(settings.job_queue))  # read by `thermofield worker --check`
    else:
        broker.emit_after("process_boot")  # the dramatiq CLI does this for its processes; it starts TimeLimit's timer
    logging.getLogger("dramatiq.worker.WorkerThread").addFilter(_ResultsGoToTheJobsTable())
    for actor in ACTORS.values():
        actor.broker, actor.queue_name = broker, settings.job_queue
        broker.declare_actor(actor)
    return broker
