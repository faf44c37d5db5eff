"""Load and soak of the scaled-out service (``make test-reliability``; deselected from the default run by the
``reliability`` marker): the real processes on PostgreSQL, RabbitMQ and Mosquitto, loaded from second
processes (benchmarks/load.py). Figures go to ``$THERMOFIELD_RELIABILITY_OUT`` for docs/reliability.md.

- load: THERMOFIELD_LOAD_SECONDS (60) of status polls and artifact downloads while scans run on two
  workers: zero errors, every scan succeeds in one attempt; throughput and p50/p99 recorded (the target of
  500 polls/s at p99 50 ms is judged from them in docs/reliability.md, not asserted).
- soak: THERMOFIELD_SOAK_SECONDS (600) of back-to-back scans: API and worker memory grow < 10 % and their
  open file descriptors do not grow (peaks of the first and the last fifth of the soak compared).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx
import psutil
import pytest

from services.formats.rig import rig_to_json
from services.simulation.presets import forging_rig

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.integration, pytest.mark.reliability]


def _record(name: str, figures: dict) -> None:
    directory = os.environ.get("THERMOFIELD_RELIABILITY_OUT")
    if directory:
        Path(directory).mkdir(parents=True, exist_ok=True)
        (Path(directory) / f"{name}.json").write_text(json.dumps(figures, indent=2))
    print(name, json.dumps(figures))


def _start(e2e, env) -> tuple[str, str]:
    """Gateway, API and worker (two processes); returns the API URL and an admin key."""
    api_url = f"http://127.0.0.1:{env['THERMOFIELD_API_PORT']}"
    env["THERMOFIELD_RATE_LIMIT_PER_S"] = "0"  # the load tools share one key
    e2e.processes.start("gateway", ["gateway"], env)
    e2e.processes.start("api", ["api"], env)
    e2e.processes.start("worker", ["worker"], env)
    e2e.processes.wait_until_healthy(f"{env['THERMOFIELD_GATEWAY_URL']}/healthz", "gateway")
    e2e.processes.wait_until_healthy(f"{api_url}/readyz", "api")
    return api_url, e2e.create_key(env, ["admin"])


def _scan(client: httpx.Client) -> dict:
    return client.post("/v1/scans").json()


def _wait_done(client: httpx.Client, job_id: str, timeout_s: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        state = client.get(f"/v1/jobs/{job_id}").json()
        if state["status"] in ("succeeded", "failed"):
            return state
        time.sleep(0.5)
    raise AssertionError(f"job {job_id} did not finish in {timeout_s} s")


def _load_process(url: str, key: str, connections: int, seconds: float) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(ROOT / "benchmarks" / "load.py"), "--url", url, "--connections",
                             str(connections), "--seconds", str(seconds), "--header", f"Authorization: Bearer {key}"],
                            stdout=subprocess.PIPE, text=True)


def _machine() -> dict:
    return {"load_average_1m": round(os.getloadavg()[0], 1), "cpus": os.cpu_count()}


@pytest.mark.timeout(1800)
def test_mixed_traffic_against_the_scaled_out_service(e2e, deployment):
    seconds = float(os.environ.get("THERMOFIELD_LOAD_SECONDS", "60"))
    api_url, key = _start(e2e, deployment)
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
        created = client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                              data={"name": "true rig", "activate": "true"})
        assert created.status_code == 201, created.text
        first = _scan(client)
        assert _wait_done(client, first["job_id"])["status"] == "succeeded", e2e.processes.log("worker")
        machine_before = _machine()
        polls = _load_process(f"{api_url}/v1/jobs/{first['job_id']}", key, 8, seconds)
        downloads = _load_process(f"{api_url}/v1/scans/{first['scan_id']}/field.ply", key, 2, seconds)
        scans, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline - 5:
            response = client.post("/v1/scans")
            assert response.status_code == 202, response.text
            scans.append(response.json())
            time.sleep(max(0.0, min(4.0, deadline - time.monotonic() - 5)))  # the test's load: a scan every 4 s
        poll_figures = json.loads(polls.communicate(timeout=seconds + 60)[0])
        download_figures = json.loads(downloads.communicate(timeout=seconds + 60)[0])
        finals = [_wait_done(client, scan["job_id"]) for scan in scans]
        workers = {final["worker"] for final in finals}
    failed = [final for final in finals if final["status"] != "succeeded" or final["attempts"] != 1]
    _record("load", {"seconds": seconds, "status_polls": poll_figures, "field_downloads": download_figures,
                     "scans": len(scans), "scans_failed_or_retried": len(failed), "worker_processes": len(workers),
                     "machine": machine_before, "machine_after": _machine()})
    assert poll_figures["errors"] == 0 and download_figures["errors"] == 0
    assert poll_figures["requests"] > 0 and download_figures["requests"] > 0
    # issue 15's throughput target (500 polls/s, p99 50 ms) is judged from these figures, not asserted: a speed
    # target in a timed test fails on a slow host, not on slow code (docs/reliability.md)
    assert not failed, failed
    assert len(workers) == 2, workers  # the scans ran on both worker processes


def _process_tree(pid: int) -> list[psutil.Process]:
    root = psutil.Process(pid)
    return [root, *root.children(recursive=True)]


def _footprint(pid: int) -> tuple[int, int]:
    """Resident memory and open file descriptors of a process and its children."""
    processes = _process_tree(pid)
    return sum(p.memory_info().rss for p in processes), sum(p.num_fds() for p in processes)


def _tree_bytes(directory: Path) -> int:
    return sum(path.stat().st_size for path in directory.rglob("*") if path.is_file())


def _peak(samples: list[dict], name: str, index: int) -> int:
    return max(sample[name][index] for sample in samples)


@pytest.mark.timeout(3600)
def test_soak_of_repeated_scans(e2e, deployment):
    """Memory and descriptors sampled after every pair of scans; the peaks of the first and the last fifth of
    the soak are compared. A worker's resident memory swings by up to ~200 MB from one scan to the next (the
    scan's temporaries returned to the system or kept by the allocator), so two single samples could differ by
    20 % with nothing leaking; a leak raises the peaks, a bounded plateau does not."""
    seconds = float(os.environ.get("THERMOFIELD_SOAK_SECONDS", "600"))
    # retention on, as a plant runs it: without it 10 minutes of scans fill tens of GB (about 100 MB a scan)
    deployment |= {"THERMOFIELD_RETENTION_KEEP_SCANS": "20", "THERMOFIELD_RETENTION_KEEP_DAYS": "0",
                   "THERMOFIELD_RETENTION_BLOB_GRACE_S": "60", "THERMOFIELD_MAINTENANCE_INTERVAL_S": "30"}
    store = Path(deployment["THERMOFIELD_ARTIFACT_DIR"])
    api_url, key = _start(e2e, deployment)
    pids = {name: process.pid for name, process in e2e.processes.running if name in ("api", "worker")}
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
        client.post("/v1/calibration-sets", files={"rig": ("rig.json", rig_to_json(forging_rig()))},
                    data={"name": "true rig", "activate": "true"})
        for _ in range(3):  # warm-up: numba compiled, tables built, pools filled in both worker processes
            warm = [_scan(client) for _ in range(2)]
            assert all(_wait_done(client, job["job_id"])["status"] == "succeeded" for job in warm)
        samples, count, deadline = [], 0, time.monotonic() + seconds
        while time.monotonic() < deadline:
            batch = [_scan(client) for _ in range(2)]
            finals = [_wait_done(client, job["job_id"]) for job in batch]
            assert all(final["status"] == "succeeded" for final in finals), finals
            count += len(batch)
            samples.append({name: _footprint(pid) for name, pid in pids.items()} | {"store": _tree_bytes(store)})
    window = max(1, len(samples) // 5)
    first, last = samples[:window], samples[-window:]
    steady = samples[window:2 * window]  # the second fifth: past the first sweeps (grace 60 s + interval 30 s)
    store_mb = {"peak_second_fifth": round(max(s["store"] for s in steady) / 1e6),
                "peak_last_fifth": round(max(s["store"] for s in last) / 1e6),
                "end": round(samples[-1]["store"] / 1e6)}
    growth = {name: {"rss_mb_peak_first": round(_peak(first, name, 0) / 1e6, 1),
                     "rss_mb_peak_last": round(_peak(last, name, 0) / 1e6, 1),
                     "rss_growth": round(_peak(last, name, 0) / _peak(first, name, 0) - 1, 4),
                     "rss_mb_min_max": [round(min(s[name][0] for s in samples) / 1e6, 1),
                                        round(max(s[name][0] for s in samples) / 1e6, 1)],
                     "fds_peak_first": _peak(first, name, 1), "fds_peak_last": _peak(last, name, 1)} for name in pids}
    _record("soak", {"seconds": seconds, "scans": count, "samples": len(samples), "window_samples": window,
                     "processes": growth, "store_mb": store_mb, "machine": _machine()})
    for name, figures in growth.items():
        assert figures["rss_growth"] < 0.10, (name, figures)
        assert figures["fds_peak_last"] <= figures["fds_peak_first"] + 2, (name, figures)  # a pooled connection or two
    assert store_mb["peak_last_fifth"] <= 1.5 * store_mb["peak_second_fifth"], store_mb  # bounded by retention
