"""CPU per status poll (``GET /v1/jobs/{id}``) of the scaled-out API on PostgreSQL, run by hand:

    python benchmarks/bench_poll.py [--polls 4000] [--seconds 10] [--repeats 3] [--baseline-tree DIR]
    python benchmarks/bench_poll.py --profile [--polls 4000]      # where the CPU goes (needs yappi)

1. In process: the ASGI app alone (every middleware, the key's digest and lookup, the rate limit, the
   query, the response, the metrics), driven by 8 concurrent callers on uvloop; the process's CPU
   seconds (every thread) per poll.
2. Over HTTP: ``thermofield api`` as its own process (RabbitMQ broker, as scaled out), polled by
   benchmarks/load.py from a second process with 8 keep-alive connections; the API process's CPU
   seconds per poll (psutil), requests/s, p50 and p99.

The polled job is a succeeded scan job with a result like a real scan's. The rate limit is on (a rate
no poll reaches), so its cost is counted. ``--baseline-tree DIR`` (e.g. ``git archive HEAD~1 | tar -x
-C DIR``) measures that tree's code the same way, alternating with this tree's, so that the ratio comes
from one run on one machine load. Each measurement runs in a child process with its tree first on
``PYTHONPATH``. Prints a Markdown table and the load average.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from statistics import median

ROOT = Path(__file__).resolve().parents[1]
POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
BROKER_URL = "amqp://guest:guest@127.0.0.1:5672"
CONNECTIONS = 8
_DIGEST = "3f" * 32


def _scan_result() -> dict:
    """The result of a scan job as the scan actor writes it (digests, summary with glow, stage seconds)."""
    names = ("cloud.ply", "field.ply", "frames.npy", "thermal.npy", "sequence.json", "exposure.json", "field.rrd")
    return {
        "scan_id": uuid.uuid4().hex,
        "artifacts": {name: _DIGEST for name in names},
        "summary": {"point_count": 493_911, "points_with_temperature": 401_207, "bbox_min": [-61.5, -40.2, 412.9],
                    "bbox_max": [88.1, 40.7, 530.4],
                    "temperature": {"min": 702.4, "max": 1043.9, "mean": 951.2,
                                    "percentiles": {"p1": 760.1, "p5": 811.7, "p50": 962.3, "p95": 1031.0,
                                                    "p99": 1040.2}},
                    "glow": {"saturated_fraction": 0.0012, "lost_fraction": 0.0104, "glow_level": 21.7,
                             "glow_drift": 0.4, "lost_to_glow": 0.0116, "exposure_mode": "fixed",
                             "exposures_us": None}},
        "stage_seconds": {"capture": 1.91, "reconstruct": 1.12, "fuse": 0.41, "store": 0.52, "stream": 0.33},
    }


def _environment(schema: str, artifact_dir: Path) -> dict[str, str]:
    return {"THERMOFIELD_DATABASE_URL": POSTGRES_URL, "THERMOFIELD_DATABASE_SCHEMA": schema,
            "THERMOFIELD_BROKER_URL": BROKER_URL, "THERMOFIELD_JOB_QUEUE": f"tf-bench-{schema}",
            "THERMOFIELD_ARTIFACT_DIR": str(artifact_dir), "THERMOFIELD_MQTT_HOST": "",
            "THERMOFIELD_RATE_LIMIT_PER_S": "1000000", "THERMOFIELD_RATE_LIMIT_BURST": "1000000"}


def _prepare(settings) -> tuple[str, str]:
    """A read key and a succeeded scan job in the settings' database: (secret, job id)."""
    from datetime import UTC, datetime

    from services.db.apikeys import create_api_key
    from services.db.models import Job
    from services.runtime import build_runtime

    runtime = build_runtime(settings)
    now = datetime.now(UTC)
    with runtime.sessions.begin() as session:
        _, secret = create_api_key(session, "bench", ["read"])
        job = Job(kind="scan", status="succeeded", stage="done", fraction=1.0, attempts=1, worker="bench:1",
                  params={"scan_id": uuid.uuid4().hex}, result=_scan_result(), started_at=now, finished_at=now)
        session.add(job)
        session.flush()
        job_id = job.id
    runtime.engine.dispose()
    return secret, job_id


async def _drive(app, path: str, secret: str, polls: int) -> None:
    """``polls`` requests through the ASGI app from ``CONNECTIONS`` concurrent callers; every answer a 200."""
    headers = [(b"host", b"127.0.0.1:8000"), (b"user-agent", b"bench"), (b"authorization", f"Bearer {secret}".encode())]
    scope = {"type": "http", "asgi": {"version": "3.0", "spec_version": "2.4"}, "http_version": "1.1",
             "method": "GET", "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
             "root_path": "", "headers": headers, "client": ("127.0.0.1", 40000), "server": ("127.0.0.1", 8000)}

    async def receive() -> dict:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def caller(count: int) -> None:
        for _ in range(count):
            statuses = []

            async def send(message: dict) -> None:
                if message["type"] == "http.response.start":
                    statuses.append(message["status"])

            await app(dict(scope, state={}), receive, send)
            if statuses != [200]:
                raise RuntimeError(f"GET {path} answered {statuses}")

    await asyncio.gather(*(caller(polls // CONNECTIONS) for _ in range(CONNECTIONS)))


def _in_process(polls: int, profile: bool) -> dict:
    """CPU seconds per poll through the ASGI app in this process (child of :func:`main`)."""
    import uvloop

    from api.app import create_app
    from services.jobs.queue import JobQueue, job_broker
    from services.runtime import build_runtime
    from services.settings import Settings

    settings = Settings()
    secret, job_id = _prepare(settings)
    runtime = build_runtime(settings)
    app = create_app(runtime, JobQueue(job_broker(settings.model_copy(update={"broker_url": ""})),
                                       settings.job_queue))
    path = f"/v1/jobs/{job_id}"
    loop = uvloop.new_event_loop()
    loop.run_until_complete(_drive(app, path, secret, 400))  # warm-up: pool, caches, imports
    if profile:
        import yappi

        yappi.set_clock_type("cpu")
        yappi.start(profile_threads=True)
    cpu, wall = time.process_time(), time.perf_counter()
    loop.run_until_complete(_drive(app, path, secret, polls))
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    if profile:
        yappi.stop()
        stats = yappi.get_func_stats()
        stats.sort("tsub")
        stats.print_all(out=sys.stderr, columns={0: ("name", 100), 1: ("ncall", 8), 2: ("tsub", 8), 3: ("ttot", 8)})
    loop.close()
    runtime.engine.dispose()
    done = polls // CONNECTIONS * CONNECTIONS
    return {"cpu_ms_per_poll": 1000 * cpu / done, "polls_per_s": done / wall}


def _over_http(seconds: float) -> dict:
    """``thermofield api`` polled by benchmarks/load.py: the API process's CPU per poll and the latencies."""
    import httpx
    import psutil

    from services.settings import Settings

    port = _free_port()
    env = os.environ | {"THERMOFIELD_API_PORT": str(port)}
    secret, job_id = _prepare(Settings())
    api = subprocess.Popen([sys.executable, "-m", "services.cli.main", "api"], env=env, stdin=subprocess.DEVNULL,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(f"{url}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if api.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("thermofield api did not start")
            time.sleep(0.3)
        command = [sys.executable, str(ROOT / "benchmarks" / "load.py"), "--url", f"{url}/v1/jobs/{job_id}",
                   "--header", f"Authorization: Bearer {secret}", "--connections", str(CONNECTIONS)]
        subprocess.run(command + ["--seconds", "2"], check=True, capture_output=True)  # warm-up
        process = psutil.Process(api.pid)
        before = process.cpu_times()
        figures = json.loads(subprocess.run(command + ["--seconds", str(seconds)], check=True, capture_output=True,
                                            text=True).stdout)
        after = process.cpu_times()
    finally:
        api.terminate()
        api.wait(timeout=30)
    if figures["errors"]:
        raise RuntimeError(f"non-200 answers: {figures}")
    cpu = (after.user - before.user) + (after.system - before.system)
    return {"cpu_ms_per_poll": 1000 * cpu / figures["requests"], "polls_per_s": figures["requests_per_s"],
            "p50_ms": figures["p50_ms"], "p99_ms": figures["p99_ms"]}


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _child(tree: Path, mode: str, args: argparse.Namespace) -> dict:
    """One measurement in a child process importing ``tree``'s code, in its own PostgreSQL schema."""
    from sqlalchemy import text

    from services.db.engine import make_engine
    from services.jobs.queue import delete_job_queues

    schema = f"tf_bench_{uuid.uuid4().hex[:10]}"
    with tempfile.TemporaryDirectory(prefix="thermofield-bench-") as artifacts:
        env = os.environ | _environment(schema, Path(artifacts)) | {"PYTHONPATH": str(tree)}
        command = [sys.executable, str(ROOT / "benchmarks" / "bench_poll.py"), "--child", mode,
                   "--polls", str(args.polls), "--seconds", str(args.seconds)]
        try:
            output = subprocess.run(command, env=env, check=True, capture_output=True, text=True,
                                    cwd=tree).stdout
        finally:
            with make_engine(POSTGRES_URL).begin() as connection:
                connection.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))
            delete_job_queues(BROKER_URL, env["THERMOFIELD_JOB_QUEUE"])
    return json.loads(output.splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--polls", type=int, default=4000)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--baseline-tree", type=Path)
    parser.add_argument("--profile", action="store_true", help="one in-process run under yappi (CPU clock), "
                                                               "functions by own time on standard error")
    parser.add_argument("--child", choices=("asgi", "http"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child == "asgi":
        print(json.dumps(_in_process(args.polls, args.profile)))
        return
    if args.child == "http":
        print(json.dumps(_over_http(args.seconds)))
        return
    if args.profile:
        schema = f"tf_bench_{uuid.uuid4().hex[:10]}"
        with tempfile.TemporaryDirectory(prefix="thermofield-bench-") as artifacts:
            os.environ.update(_environment(schema, Path(artifacts)))
            try:
                print(json.dumps(_in_process(args.polls, profile=True)))
            finally:
                from sqlalchemy import text

                from services.db.engine import make_engine

                with make_engine(POSTGRES_URL).begin() as connection:
                    connection.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))
        return

    trees = {"this tree": ROOT} | ({"baseline": args.baseline_tree.resolve()} if args.baseline_tree else {})
    load_before = os.getloadavg()[0]
    runs: dict[tuple[str, str], list[dict]] = {}
    for _ in range(args.repeats):
        for mode in ("asgi", "http"):
            for label, tree in trees.items():
                runs.setdefault((label, mode), []).append(_child(tree, mode, args))
    load_after = os.getloadavg()[0]
    print(f"## GET /v1/jobs/{{id}}: CPU per poll ({args.repeats} repeats, medians; {CONNECTIONS} concurrent)\n")
    print("| code | path | CPU ms per poll | polls/s | p50 ms | p99 ms |\n|---|---|---|---|---|---|")
    for (label, mode), results in runs.items():
        cells = [f"{median(r['cpu_ms_per_poll'] for r in results):.3f}",
                 f"{median(r['polls_per_s'] for r in results):.0f}"]
        cells += [f"{median(r[name] for r in results):.1f}" if mode == "http" else "-" for name in ("p50_ms", "p99_ms")]
        path = "ASGI app in process" if mode == "asgi" else "`thermofield api` over HTTP"
        print(f"| {label} | {path} | " + " | ".join(cells) + " |")
    if args.baseline_tree:
        for mode in ("asgi", "http"):
            ratio = (median(r["cpu_ms_per_poll"] for r in runs[("baseline", mode)])
                     / median(r["cpu_ms_per_poll"] for r in runs[("this tree", mode)]))
            print(f"\nCPU per poll, baseline / this tree ({mode}): {ratio:.2f}")
    print(f"\nLoad average: {load_before:.1f} -> {load_after:.1f} on {os.cpu_count()} cores.")


if __name__ == "__main__":
    main()
