"""Cross-cutting concerns of every actor: job bookkeeping and numeric thread counts."""

from __future__ import annotations

import logging
import os
import socket
import sys
import threading

import cv2
import dramatiq
from dramatiq.middleware import Middleware, SkipMessage

from services.jobs.tracker import CONTINUATION, CONTINUED, LEASE_S, JobBusy
from services.structured_light.row_bands import limit_threads
from services.runtime import current_runtime

logger = logging.getLogger(__name__)
class ComputeThreads(Middleware):
    """Caps the numeric thread pools (OpenCV's, the science's row bands, numba's where it is loaded) in each
    worker process so that replicas share the cores."""

    def __init__(self, threads: int) -> None:
        self.threads = threads

    def before_worker_boot(self, broker, worker) -> None:
        cv2.setNumThreads(self.threads)
        limit_threads(self.threads)
        if "numba" not in sys.modules:  # read by numba when first imported; once loaded, numba refuses a change
            os.environ["NUMBA_NUM_THREADS"] = str(self.threads)

    def after_worker_thread_boot(self, broker, thread) -> None:
        # numba (only the Gray-code-only refinement and the simulator use it) sets its count per calling thread
        if "numba" in sys.modules:
            numba = sys.modules["numba"]
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
    ``failed`` when it will not. While it runs, a thread renews the job's lease. A
    message whose job already finished, or runs elsewhere and that is not the broker's
    redelivery (a duplicate), is skipped; a redelivery while the job's lease is live (the
    broker lost its connection to a worker that still runs it) is sent again after a
    while, and runs only once the lease has run out
    (:meth:`services.jobs.tracker.JobTracker.start`).
    """

    def __init__(self) -> None:
        self._leases: dict[str, threading.Event] = {}
        self._lock = threading.Lock()

    def before_process_message(self, broker, message) -> None:
        job_id, worker = message.args[0], f"{socket.gethostname()}:{os.getpid()}"
        # RabbitMQ's redelivery flag (the stub broker has none), kept on the copies sent while the job was busy.
        redelivered = bool(getattr(message, "redelivered", False) or message.options.get("redelivered"))
        tracker = current_runtime().tracker
        try:
            job = tracker.start(job_id, worker, redelivered, continuation=bool(message.options.get(CONTINUATION)))
        except JobBusy as busy:
            logger.info("Message %s waits: %s.", message.message_id, busy)
            broker.enqueue(message.copy(options={"redelivered": True}), delay=int(LEASE_S * 500))
            raise SkipMessage() from None
        if job is None:
            logger.info("Skipping message %s: job %s is unknown, finished or running elsewhere.",
                        message.message_id, job_id)
            raise SkipMessage()
        stop = threading.Event()
        with self._lock:
            self._leases[message.message_id] = stop
        threading.Thread(target=_renew_lease, args=(tracker, job_id, worker, stop), name=f"lease-{job_id}",
                         daemon=True).start()

    def after_process_message(self, broker, message, *, result=None, exception=None) -> None:
        with self._lock:
            lease = self._leases.pop(message.message_id, None)
        if lease is not None:
            lease.set()
        tracker = current_runtime().tracker
        job_id = message.args[0]
        if exception is None:
            if isinstance(result, dict) and CONTINUED in result:
                tracker.hand_over(job_id, result)
            else:
                tracker.succeed(job_id, result or {})
            return
        tracker.fail(job_id, _describe(exception), will_retry=_will_retry(broker, message, exception))


def _renew_lease(tracker, job_id: str, worker: str, stop: threading.Event) -> None:
    while not stop.wait(LEASE_S / 5):
        try:
            tracker.beat(job_id, worker)
        except Exception:  # the database is away for a moment: the next beat may reach it
            logger.warning("could not renew the lease of job %s", job_id, exc_info=True)


def _will_retry(broker: dramatiq.Broker, message: dramatiq.Message, exception: BaseException) -> bool:
    # This middleware is added after Retries, so it sees the message before Retries counts the attempt.
    actor = broker.get_actor(message.actor_name)
    throws = actor.options.get("throws")
    if throws and isinstance(exception, throws):
        return False
    return message.options.get("retries", 0) < actor.options.get("max_retries", 0)


def _describe(exception: BaseException) -> str:
    return f"{type(exception).__name__}: {exception}" if str(exception) else type(exception).__name__

