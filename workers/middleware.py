"""Cross-cutting concerns of every actor: job bookkeeping and numeric thread counts."""

from __future__ import annotations

import logging
import os
import socket
import threading

import cv2
import dramatiq
import numba
from dramatiq.middleware import Middleware, SkipMessage

from services.runtime import current_runtime

logger = logging.getLogger(__name__)
class ComputeThreads(Middleware):
    """Caps OpenCV's and numba's thread pools in each worker process so that replicas share the cores."""

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def before_worker_boot(self, broker, worker) -> None:
        cv2.setNumThreads(self.threads)

    def after_worker_thread_boot(self, broker, thread) -> None:
        # numba's thread count is per calling thread, so each worker thread sets its own.
        numba.set_num_threads(min(self.threads, numba.config.NUMBA_NUM_THREADS))


class WarmUp(Middleware):
    """Warms each worker process up when it boots, so that its first job is as fast as the next."""

    def after_worker_boot(self, broker, worker) -> None:
        from workers.actors import warm_up_runtime

        runtime = current_runtime()
        runtime.ready.clear()
        threading.Thread(target=warm_up_runtime, args=(runtime,), name="warm-up", daemon=True).start()


class JobBookkeeping(Middleware):
    """Keeps the jobs table in step with message processing.

    Each message carries a job id as its first argument. Before the actor runs the
    job becomes ``running`` (a new attempt); afterwards ``succeeded`` with the
    actor's result, or ``queued`` again when the Retries middleware will retry, or
    ``failed`` when it will not. A message whose job already finished, or runs elsewhere
    and that is not the broker's redelivery of a dead worker's message (a duplicate), is
    skipped (:meth:`services.jobs.tracker.JobTracker.start`).
    """

    def before_process_message(self, broker, message) -> None:
        job_id = message.args[0]
        redelivered = bool(getattr(message, "redelivered", False))  # RabbitMQ's flag; the stub broker has none
        if current_runtime().tracker.start(job_id, f"{socket.gethostname()}:{os.getpid()}", redelivered) is None:
            logger.info("Skipping message %s: job %s is unknown, finished or running elsewhere.",
                        message.message_id, job_id)
            raise SkipMessage()

    def after_process_message(self, broker, message, *, result=None, exception=None) -> None:
        tracker = current_runtime().tracker
        job_id = message.args[0]
        if exception is None:
            tracker.succeed(job_id, result or {})
            return
        tracker.fail(job_id, _describe(exception), will_retry=_will_retry(broker, message, exception))


def _will_retry(broker: dramatiq.Broker, message: dramatiq.Message, exception: BaseException) -> bool:
    # This middleware is added after Retries, so it sees the message before Retries counts the attempt.
    actor = broker.get_actor(message.actor_name)
    throws = actor.options.get("throws")
    if throws and isinstance(exception, throws):
        return False
    return message.options.get("retries", 0) < actor.options.get("max_retries", 0)


def _describe(exception: BaseException) -> str:
    return f"{type(exception).__name__}: {exception}" if str(exception) else type(exception).__name__

