import time

import dramatiq

from services.db.engine import make_sessions
from services.db.models import Job
from services.jobs.tracker import JobTracker


def run_jobs(broker, actor, count):
    tracker = JobTracker(make_sessions(broker_runtime_engine(broker)))
    with tracker.sessions.begin() as session:
        ids = [tracker.create(session, actor.actor_name, {"index": i}).id for i in range(count)]
    for job_id in ids:
        actor.send(job_id)
    worker = dramatiq.Worker(broker, worker_threads=2, worker_timeout=50)
    worker.start()
    broker.join(actor.queue_name, timeout=20_000, fail_fast=False)
    worker.join()
    worker.stop()
    with tracker.sessions() as session:
        return [session.get(Job, job_id) for job_id in ids]


def broker_runtime_engine(broker):
    from services.runtime import current_runtime

    return current_runtime().engine


def test_success_records_the_result_as_the_jobs_result(broker):
    @dramatiq.actor(broker=broker, actor_name="t_ok", queue_name="t_ok", max_retries=0)
    def ok(job_id):
        return {"job": job_id}

    jobs = run_jobs(broker, ok, 3)
    assert all(job.status == "succeeded" and job.result == {"job": job.id} and job.attempts == 1 for job in jobs)


def test_bad_input_fails_at_once_and_names_the_error(broker):
    @dramatiq.actor(broker=broker, actor_name="t_bad", queue_name="t_bad", max_retries=3, throws=(ValueError,))
    def bad(job_id):
        raise ValueError("rig.json: devices.camera.K: focal lengths must be positive")

    (job,) = run_jobs(broker, bad, 1)
    assert (job.status, job.attempts) == ("failed", 1)
    assert job.error == "ValueError: rig.json: devices.camera.K: focal lengths must be positive"


def test_transient_errors_are_retried_up_to_the_actors_limit(broker):
    calls = []

    @dramatiq.actor(broker=broker, actor_name="t_flaky", queue_name="t_flaky", max_retries=2,
                    min_backoff=10, max_backoff=20)
    def flaky(job_id):
        calls.append(job_id)
        if len(calls) < 3:
            raise ConnectionError("gateway lost")
        return {}

    (job,) = run_jobs(broker, flaky, 1)
    assert (job.status, job.attempts, job.error) == ("succeeded", 3, None)


def test_exhausted_retries_fail_the_job(broker):
    @dramatiq.actor(broker=broker, actor_name="t_down", queue_name="t_down", max_retries=1,
                    min_backoff=10, max_backoff=20)
    def down(job_id):
        raise ConnectionError("gateway unreachable")

    (job,) = run_jobs(broker, down, 1)
    assert (job.status, job.attempts, job.error) == ("failed", 2, "ConnectionError: gateway unreachable")


def test_time_limit_stops_a_stuck_job(broker):
    @dramatiq.actor(broker=broker, actor_name="t_slow", queue_name="t_slow", max_retries=0, time_limit=300)
    def slow(job_id):
        for _ in range(100):
            time.sleep(0.05)  # the test: a job stuck past its time limit

    (job,) = run_jobs(broker, slow, 1)
    assert job.status == "failed" and job.error.startswith("TimeLimitExceeded")


def test_duplicate_delivery_of_a_finished_job_is_skipped(broker):
    calls = []

    @dramatiq.actor(broker=broker, actor_name="t_once", queue_name="t_once", max_retries=0)
    def once(job_id):
        calls.append(job_id)

    (job,) = run_jobs(broker, once, 1)
    once.send(job.id)
    worker = dramatiq.Worker(broker, worker_threads=1, worker_timeout=50)
    worker.start()
    broker.join(once.queue_name, timeout=10_000, fail_fast=False)
    worker.stop()
    assert calls == [job.id]


def test_service_actors_set_their_own_retries_and_time_limits(broker):
    from workers.actors import ACTORS

    for actor in ACTORS.values():
        assert actor.broker is broker
        assert {"max_retries", "time_limit", "throws"} <= set(actor.options), actor.actor_name


def test_worker_threads_use_the_configured_numeric_thread_count(broker):
    import cv2
    import numba

    from services.structured_light.row_bands import thread_count

    @dramatiq.actor(broker=broker, actor_name="t_threads", queue_name="t_threads", max_retries=0)
    def threads(job_id):
        return {"numba": numba.get_num_threads(), "row_bands": thread_count(), "opencv": cv2.getNumThreads()}

    (job,) = run_jobs(broker, threads, 1)
    assert job.result == {"numba": 1, "row_bands": 1, "opencv": 1}  # the fixture's compute_threads



def test_a_second_worker_in_a_process_whose_numba_runs_leaves_numbas_thread_count_alone():
    """The embedded service and the tests boot several workers in one process: once numba has launched its
    threads it refuses another NUMBA_NUM_THREADS at its next configuration reload (a compile), so a later
    worker's boot must not set a different one."""
    import subprocess
    import sys

    program = (
        "import os; os.environ['NUMBA_NUM_THREADS'] = '1'\n"
        "import numba, numpy as np\n"
        "numba.njit(parallel=True)(lambda a: a.sum())(np.ones(4))\n"  # launches numba's threads
        "from workers.middleware import ComputeThreads\n"
        "ComputeThreads(2).before_worker_boot(None, None)\n"
        "numba.core.config.reload_config()\n"  # what numba's next compile does
        "print(numba.config.NUMBA_NUM_THREADS)\n")
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-1000:]
    assert done.stdout.strip() == "1"
