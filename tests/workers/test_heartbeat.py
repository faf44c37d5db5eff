"""Worker heartbeats: what the worker container's healthcheck reads."""

import os
import subprocess
import sys
import uuid

import dramatiq
from dramatiq.brokers.stub import StubBroker

from workers.heartbeat import Heartbeat, live_worker_processes


def test_the_heartbeat_tells_the_healthcheck_that_each_worker_process_lives():
    queue = f"t-heartbeat-{uuid.uuid4().hex[:8]}"
    check = [sys.executable, "-m", "services.cli.main", "worker", "--check"]
    env = os.environ | {"THERMOFIELD_JOB_QUEUE": queue, "THERMOFIELD_WORKER_PROCESSES": "1"}
    broker = StubBroker()
    broker.add_middleware(Heartbeat(queue))
    assert live_worker_processes(queue) == 0
    assert subprocess.run(check, env=env, capture_output=True, timeout=120).returncode == 1
    worker = dramatiq.Worker(broker, worker_threads=1)
    worker.start()
    try:
        assert live_worker_processes(queue) == 1
        assert live_worker_processes(queue, max_age_s=-1) == 0  # a stale heartbeat does not count
        result = subprocess.run(check, env=env, capture_output=True, text=True, timeout=120)
        assert result.returncode == 0 and "1 of 1 processes alive" in result.stdout, result
    finally:
        worker.stop()
    assert live_worker_processes(queue) == 0
