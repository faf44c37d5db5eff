"""A station scan of the simulated four-head station: from the capture's last frame to the merged field and the
verdict stored, embedded and scaled out.

Run by hand (not a test):

    .venv/bin/python benchmarks/bench_station.py [--scale 1.0] [--repeats 5] [--skip-embedded] [--skip-scaled-out]

Each scan is inspected against the nominal shaft (``hot_part.write_shaft_part``). Its latency is the job's
``finished_at`` (the field, the report, the recording and the summary stored) minus the capture's last frame
(``last_frame_at`` in the job's result: the last thermal frame, taken after every head filmed), both wall-clock
on this machine; the first scan after a start is left out of the median (warm-up). Three deployments:

- **embedded**: ``thermofield serve`` (its in-process worker; ``THERMOFIELD_WORKER_THREADS`` 1, the default: the
  heads' messages one after another in the one process);
- **one worker** and **two workers**: ``thermofield api`` and ``thermofield worker`` with
  ``THERMOFIELD_WORKER_PROCESSES`` 1 or 2, on PostgreSQL and RabbitMQ, sharing one ``thermofield gateway``; each
  its own database schema and job queue. The speed-up is the one-worker median over the two-worker median,
  measured in the same run.

Reports each deployment's latencies, median and the per-stage seconds of the median scan (from the job's
``stage_seconds``: each head's reconstruction, the merge, the fusion, the inspection, the stream, the store).
"""

from __future__ import annotations

import argparse
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from datetime import datetime
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
THERMOFIELD = [sys.executable, "-m", "services.cli.main"]
POSTGRES = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
RABBITMQ = "amqp://guest:guest@127.0.0.1:5672"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class _Processes:
    def __init__(self, logs: Path) -> None:
        self.logs, self.running = logs, []

    def start(self, name: str, arguments: list[str], env: dict[str, str]) -> subprocess.Popen:
        log = open(self.logs / f"{name}.log", "wb")
        process = subprocess.Popen(THERMOFIELD + arguments, env=os.environ | env, stdout=log, stderr=subprocess.STDOUT,
                                   stdin=subprocess.DEVNULL, start_new_session=True, cwd=ROOT)
        self.running.append(process)
        return process

    def stop_all(self) -> None:
        for process in reversed(self.running):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
                try:
                    process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(process.pid, signal.SIGKILL)
        self.running = []


def _wait_healthy(url: str, timeout_s: float = 900.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    raise SystemExit(f"{url} did not answer within {timeout_s} s")


def _key(env: dict[str, str]) -> str:
    return subprocess.run(THERMOFIELD + ["apikey", "create", "--scopes", "admin"], env=os.environ | env, cwd=ROOT,
                          capture_output=True, text=True, check=True).stdout.strip()


def _scans(api_url: str, key: str, repeats: int, part_dir: Path, rig_json: bytes | None) -> list[dict]:
    """``repeats`` + 1 scans one after another; each job's final state."""
    from services.simulation.hot_part import write_shaft_part

    part = write_shaft_part(part_dir)
    states = []
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {key}"}, timeout=120) as client:
        if rig_json is not None:
            created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_json)},
                                  data={"name": "station", "activate": "true"})
            created.raise_for_status()
        created = client.post("/v1/part-types", files={"part": ("part.json", part.read_bytes()),
                                                       "mesh": ("shaft.stl", (part.parent / "shaft.stl").read_bytes())})
        created.raise_for_status()
        part_type = created.json()["part_type_id"]
        for _ in range(repeats + 1):
            job = client.post("/v1/scans", json={"part_type_id": part_type}).json()["job_id"]
            while (state := client.get(f"/v1/jobs/{job}").json())["status"] not in ("succeeded", "failed"):
                time.sleep(0.05)
            if state["status"] != "succeeded":
                raise SystemExit(f"scan job failed: {state['error']}")
            states.append(state)
    return states


def _latency(state: dict) -> float:
    finished = datetime.fromisoformat(state["finished_at"].replace("Z", "+00:00")).timestamp()
    return finished - state["result"]["last_frame_at"]


def _report(name: str, states: list[dict]) -> tuple[float, dict]:
    latencies = [_latency(state) for state in states[1:]]
    median = statistics.median(latencies)
    middle = min(states[1:], key=lambda state: abs(_latency(state) - median))
    print(f"{name}: last frame -> stored, s: {', '.join(f'{x:.2f}' for x in latencies)} "
          f"(first {_latency(states[0]):.2f}); median {median:.2f}; verdict {middle['result'].get('verdict')}",
          flush=True)
    print(f"  stages of the median scan: {middle['result']['stage_seconds']}", flush=True)
    return median, middle["result"]["stage_seconds"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", type=float, default=1.0, help="the simulated station's image scale")
    parser.add_argument("--repeats", type=int, default=5, help="scans timed per deployment (after a first one)")
    parser.add_argument("--skip-embedded", action="store_true")
    parser.add_argument("--skip-scaled-out", action="store_true")
    args = parser.parse_args()
    from services.formats.rig import rig_to_json
    from services.simulation.presets import station_rig

    station = {"THERMOFIELD_SIMULATED_STATION_HEADS": "4", "THERMOFIELD_SIMULATED_STATION_SCALE": str(args.scale),
               "THERMOFIELD_CAMERA_EXPOSURE_MODE": "auto", "THERMOFIELD_RERUN_WEB_PORT": ""}
    results = {}
    with tempfile.TemporaryDirectory(prefix="bench-station-") as tmp:
        tmp = Path(tmp)
        processes = _Processes(tmp)
        try:
            if not args.skip_embedded:
                port = _free_port()
                env = station | {"THERMOFIELD_DATA_DIR": str(tmp / "embedded"), "THERMOFIELD_SITE": "bench-station"}
                processes.start("serve", ["serve", "--port", str(port), "--gateway-port", str(_free_port()),
                                          "--rerun-port", str(_free_port())], env)
                _wait_healthy(f"http://127.0.0.1:{port}/readyz")
                states = _scans(f"http://127.0.0.1:{port}", _key(env), args.repeats, tmp / "part", None)
                results["embedded"] = _report("embedded", states)
                processes.stop_all()
            if not args.skip_scaled_out:
                gateway_port = _free_port()
                gateway_env = station | {"THERMOFIELD_GATEWAY_PORT": str(gateway_port)}
                processes.start("gateway", ["gateway"], gateway_env)
                _wait_healthy(f"http://127.0.0.1:{gateway_port}/healthz")
                for workers in (1, 2):
                    tag = uuid.uuid4().hex[:8]
                    api_port = _free_port()
                    env = station | {"THERMOFIELD_DATABASE_URL": POSTGRES, "THERMOFIELD_DATABASE_SCHEMA": f"bench_{tag}",
                                     "THERMOFIELD_BROKER_URL": RABBITMQ, "THERMOFIELD_JOB_QUEUE": f"bench-{tag}",
                                     "THERMOFIELD_ARTIFACT_DIR": str(tmp / f"artifacts-{workers}"),
                                     "THERMOFIELD_GATEWAY_URL": f"http://127.0.0.1:{gateway_port}",
                                     "THERMOFIELD_API_PORT": str(api_port), "THERMOFIELD_RERUN_PORT": str(_free_port()),
                                     "THERMOFIELD_SITE": f"bench-{tag}", "THERMOFIELD_WORKER_PROCESSES": str(workers)}
                    api = processes.start(f"api-{workers}", ["api"], env)
                    worker = processes.start(f"worker-{workers}", ["worker"], env)
                    _wait_healthy(f"http://127.0.0.1:{api_port}/readyz")
                    rig = rig_to_json(station_rig(args.scale, 4)).encode()
                    states = _scans(f"http://127.0.0.1:{api_port}", _key(env), args.repeats, tmp / f"part-{workers}",
                                    rig)
                    results[f"{workers} worker{'s' if workers > 1 else ''}"] = _report(
                        f"scaled out, {workers} worker process(es)", states)
                    for process in (worker, api):
                        os.killpg(process.pid, signal.SIGTERM)
                        process.wait(timeout=60)
                    _drop(env)
        finally:
            processes.stop_all()
    if "1 worker" in results and "2 workers" in results:
        print(f"speed-up, two worker processes against one: {results['1 worker'][0] / results['2 workers'][0]:.2f}x")


def _drop(env: dict[str, str]) -> None:
    from sqlalchemy import text

    from services.db.engine import make_engine
    from services.jobs.queue import delete_job_queues

    with make_engine(POSTGRES).begin() as connection:
        connection.execute(text(f"DROP SCHEMA IF EXISTS {env['THERMOFIELD_DATABASE_SCHEMA']} CASCADE"))
    delete_job_queues(RABBITMQ, env["THERMOFIELD_JOB_QUEUE"])


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main()
