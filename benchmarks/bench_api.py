"""Service benchmarks on the embedded default (`thermofield serve`), run by hand:

    .venv/bin/python benchmarks/bench_api.py [--scans 5] [--seconds 5] [--repeats 3]

1. Scan latency: from ``POST /v1/scans`` to the ``done`` server-sent event (field ready), for a
   1280x800 structured-light capture and one 320x256 thermal frame from the simulated gateway;
   median over ``--scans`` scans after one warm-up, with the per-stage seconds the job records.
   Baseline in the same run: the same science without the service (gateway capture, reconstruct,
   fuse, in this process), so the ratio is the service's overhead.
2. ``GET /v1/jobs/{id}`` throughput and p99 latency with benchmarks/load.py from a second process,
   at 8 and 16 keep-alive connections, medians over ``--repeats`` runs. Baseline: ``GET /healthz``
   (no key, no database) in the same run.

Prints Markdown tables for docs/api.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from statistics import median

import httpx

ROOT = Path(__file__).resolve().parents[1]
THERMOFIELD = [sys.executable, "-m", "services.cli.main"]


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _scan_seconds(client: httpx.Client) -> tuple[float, dict]:
    start = time.perf_counter()
    job_id = client.post("/v1/scans").json()["job_id"]
    with client.stream("GET", f"/v1/jobs/{job_id}/events", timeout=600) as response:
        for line in response.iter_lines():
            if line.startswith("event: done"):
                break
    elapsed = time.perf_counter() - start
    job = client.get(f"/v1/jobs/{job_id}").json()
    if job["status"] != "succeeded":
        raise RuntimeError(f"scan job failed: {job['error']}")
    return elapsed, job["result"]["stage_seconds"]


def _science_alone_seconds(gateway_url: str) -> float:
    """Capture, reconstruct and fuse without the service: the baseline of the scan latency."""
    from device_gateway.client import GatewayClient
    from services.fusion.field import temperature_field
    from services.fusion.fuse import ThermalView

    from services.simulation.presets import forging_rig
    from services.structured_light.reconstruct import reconstruct_points
    from services.structured_light.triangulate import triangulation_table

    rig = forging_rig()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    table = triangulation_table(camera, projector, "x")
    start = time.perf_counter()
    with GatewayClient(gateway_url) as gateway:
        capture = gateway.capture()
    cloud = reconstruct_points(capture.frames, capture.sequence, camera, projector, table=table)
    temperature_field(cloud, [ThermalView(thermal, capture.thermal)], camera.centre)
    return time.perf_counter() - start


def _load(url: str, headers: list[str], connections: int, seconds: float) -> dict:
    command = [sys.executable, str(ROOT / "benchmarks" / "load.py"), "--url", url, "--connections", str(connections),
               "--seconds", str(seconds)]
    for header in headers:
        command += ["--header", header]
    return json.loads(subprocess.run(command, capture_output=True, text=True, check=True).stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=5)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    data_dir = Path(tempfile.mkdtemp(prefix="thermofield-bench-"))
    port, gateway_port = _free_port(), _free_port()
    # The load measures the API itself, not the per-key rate limit (off here).
    env = os.environ | {"THERMOFIELD_DATA_DIR": str(data_dir), "THERMOFIELD_SITE": "bench",
                        "THERMOFIELD_RATE_LIMIT_PER_S": "0"}
    serve = subprocess.Popen(THERMOFIELD + ["serve", "--port", str(port), "--gateway-port", str(gateway_port),
                                            "--rerun-port", str(_free_port()), "--rerun-web-port", str(_free_port())],
                             env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{port}"
        while True:
            try:
                if httpx.get(f"{base}/readyz", timeout=1).status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.5)
        key = subprocess.run(THERMOFIELD + ["apikey", "create", "--scopes", "operate"], env=env, check=True,
                             capture_output=True, text=True).stdout.strip()
        with httpx.Client(base_url=base, headers={"Authorization": f"Bearer {key}"}, timeout=60) as client:
            warm_up, _ = _scan_seconds(client)
            runs = [_scan_seconds(client) for _ in range(args.scans)]
            job_id = client.get("/v1/jobs", params={"limit": 1}).json()[0]["job_id"]
        science = [_science_alone_seconds(f"http://127.0.0.1:{gateway_port}") for _ in range(args.scans)]
        scan_median = median(seconds for seconds, _ in runs)
        stages = {name: median(stage[name] for _, stage in runs) for name in runs[0][1]}
        print(f"## Scan: POST /v1/scans to field ready ({args.scans} scans, after a {warm_up:.2f} s warm-up)\n")
        print("| measurement | median s |\n|---|---|")
        print(f"| POST to `done` event (service) | {scan_median:.2f} |")
        for name, seconds in stages.items():
            print(f"| - stage {name} | {seconds:.2f} |")
        print(f"| baseline: capture + reconstruct + fuse alone | {median(science):.2f} |")
        print(f"| ratio service / baseline | {scan_median / median(science):.2f} |\n")

        print(f"## GET /v1/jobs/{{id}} from a second process ({args.repeats} x {args.seconds:.0f} s, medians)\n")
        print("| endpoint | connections | requests/s | p50 ms | p99 ms |\n|---|---|---|---|---|")
        for connections in (8, 16):
            for label, path, headers in (("GET /v1/jobs/{id}", f"/v1/jobs/{job_id}", [f"Authorization: Bearer {key}"]),
                                         ("baseline GET /healthz", "/healthz", [])):
                results = [_load(base + path, headers, connections, args.seconds) for _ in range(args.repeats)]
                if any(result["errors"] for result in results):
                    raise RuntimeError(f"{label}: non-200 answers: {results}")
                print(f"| {label} | {connections} | {median(r['requests_per_s'] for r in results):.0f} | "
                      f"{median(r['p50_ms'] for r in results):.1f} | {median(r['p99_ms'] for r in results):.1f} |")
        print(f"\nMachine load average during the run: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.")
    finally:
        serve.terminate()
        serve.wait(timeout=30)


if __name__ == "__main__":
    main()
