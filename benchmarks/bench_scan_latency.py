"""Embedded service: from ``POST /v1/scans`` to the field ready, the first scan after a start included.

Run by hand (not a test):

    .venv/bin/python benchmarks/bench_scan_latency.py [--scans 8] [--follow events|poll] [--out docs/benchmark-scan.md]

Starts ``thermofield serve`` (fresh data directory, free ports), waits for ``/readyz`` (the worker has
warmed up: kernels compiled, the active calibration's triangulation table built), then runs ``--scans``
scans one after the other: each is timed from the POST to its job's ``succeeded``, which is when the field,
its PLY, its Rerun recording and the summary are stored, as a client learns it: by following the job's
server-sent events (``--follow events``, the default, as a station's MES would; the service looks at the job
every 100 ms) or by polling ``GET /v1/jobs/{id}`` every 20 ms (``--follow poll``: each poll costs the
service's API thread CPU beside the worker). Reports every scan's
latency, their median, the start-to-ready time, the CPU time each scan cost the service and the gateway
processes (user + system, from ``/proc``: on a machine shared with other work the latency grows with the
load, the CPU time much less), and the peak resident memory (``VmHWM``) of the service process, which runs
the API and the worker, and of the gateway process.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (all its threads)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(") ", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if int((entry / "stat").read_text().split(") ")[1].split()[1]) == pid:
                    found.append(int(entry.name))
            except (OSError, IndexError, ValueError):
                continue
    return found


def _wait_until_finished(client: httpx.Client, job_url: str, follow: str) -> None:
    """Return once the job has finished, learnt as ``follow`` says."""
    if follow == "events":
        with client.stream("GET", f"{job_url}/events") as events:
            for line in events.iter_lines():
                if line.startswith("data:") and json.loads(line.removeprefix("data:"))["status"] in _FINISHED:
                    break
    else:
        while client.get(job_url).json()["status"] not in _FINISHED:
            time.sleep(0.02)


_FINISHED = ("succeeded", "failed")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=8)
    parser.add_argument("--follow", choices=("events", "poll"), default="events",
                        help="learn that a scan finished from its job's events (default) or by polling the job")
    parser.add_argument("--out", type=Path, help="also write the table as Markdown")
    args = parser.parse_args()
    env = os.environ | {"PYTHONPATH": str(ROOT), "THERMOFIELD_MQTT_HOST": ""}
    with tempfile.TemporaryDirectory() as data:
        port = _free_port()
        key = subprocess.run([sys.executable, "-m", "services.cli.main", "apikey", "create", "--scopes", "read",
                              "operate", "--data-dir", data], env=env, capture_output=True, text=True, check=True)
        secret = key.stdout.splitlines()[0].strip()
        started = time.perf_counter()
        server = subprocess.Popen([sys.executable, "-m", "services.cli.main", "serve", "--data-dir", data,
                                   "--port", str(port), "--gateway-port", str(_free_port()),
                                   "--rerun-port", str(_free_port()), "--rerun-web-port", str(_free_port())], env=env, cwd=ROOT,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        latencies, stages, service_cpu, gateway_cpu = [], [], [], []
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", headers={"Authorization": f"Bearer {secret}"},
                              timeout=60) as client:
                while True:
                    try:
                        if client.get("/readyz").status_code == 200:
                            break
                    except httpx.TransportError:
                        pass
                    if server.poll() is not None or time.perf_counter() - started > 600:
                        raise RuntimeError("the service did not become ready")
                    time.sleep(0.1)
                ready_s = time.perf_counter() - started
                gateway = _children(server.pid)
                for _ in range(args.scans):
                    cpu_before = _cpu_s(server.pid), sum(map(_cpu_s, gateway))
                    start = time.perf_counter()
                    job_url = client.post("/v1/scans", json={}).headers["Location"]
                    _wait_until_finished(client, job_url, args.follow)
                    latencies.append(time.perf_counter() - start)
                    service_cpu.append(_cpu_s(server.pid) - cpu_before[0])
                    gateway_cpu.append(sum(map(_cpu_s, gateway)) - cpu_before[1])
                    job = client.get(job_url).json()
                    if job["status"] != "succeeded":
                        raise RuntimeError(f"scan failed: {job['error']}")
                    stages.append(job["result"]["stage_seconds"])
            service_mb = _peak_rss_mb(server.pid)
            gateway_mb = max((_peak_rss_mb(pid) for pid in _children(server.pid)), default=float("nan"))
        finally:
            os.killpg(server.pid, signal.SIGTERM)
            server.wait(timeout=60)
    load = os.getloadavg()
    lines = [f"Load average {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f} (1/5/15 min) on {os.cpu_count()} cores "
             f"while it ran; the client followed each job by {'its events' if args.follow == 'events' else 'polling'}.",
             "",
             "| what | value | target |", "|---|---|---|",
             f"| start to `/readyz` ready (warm-up included) | {ready_s:.1f} s | |",
             f"| first scan after the start, POST to field ready | {latencies[0]:.3f} s | at most 1.0 s |",
             f"| median of {len(latencies)} scans (the first included) | {statistics.median(latencies):.3f} s | "
             "at most 1.0 s |",
             f"| all scans | {', '.join(f'{s:.3f}' for s in latencies)} s | |",
             f"| stages of the first scan (worker) | {stages[0]} | |",
             f"| stages of the median scan (worker) | {stages[latencies.index(statistics.median(latencies))] if len(latencies) % 2 else stages[len(stages) // 2]} | |",
             f"| CPU time per scan, median: service (API + worker) / gateway | {statistics.median(service_cpu):.2f} / "
             f"{statistics.median(gateway_cpu):.2f} s | |",
             f"| peak memory of the service process (API + worker) | {service_mb:.0f} MB | reported |",
             f"| peak memory of the gateway process | {gateway_mb:.0f} MB | reported |"]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
