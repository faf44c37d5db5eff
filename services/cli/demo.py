"""``thermofield demo``: the embedded service end to end, as an MES would use it.

Starts ``thermofield serve`` (API, in-process worker, simulated gateway, SQLite, artifact directory,
Rerun proxy), creates an API key, scans the simulated hot part through ``POST /v1/scans``, follows the
job's server-sent events, prints the field's summary, downloads ``field.ply`` and ``field.rrd``, and
says how to watch it in Rerun.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from services.errors import InputError
from services.formats.files import atomic_output

_STARTUP_TIMEOUT_S = 180.0
_SCAN_TIMEOUT_S = 600.0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "demo",
        description=__doc__.splitlines()[0],
    )
    parser.add_argument("--data-dir", type=Path, default=Path("demo-output"),
                        help="service data directory (default ./demo-output)")
    parser.add_argument("--port", type=int, default=8000, help="API port (default 8000)")
    parser.add_argument("--gateway-port", type=int, default=8001, help="simulated gateway port (default 8001)")
    parser.add_argument("--rerun-port", type=int, default=9876, help="Rerun gRPC proxy port (default 9876)")
    parser.add_argument("--exit-after-scan", action="store_true",
                        help="stop the service once the scan is saved (default: keep serving until Ctrl-C)")
    parser.set_defaults(handler=_run)


def _thermofield(*args: str) -> list[str]:
    return [sys.executable, "-m", "services.cli.main", *args]


def _wait_until_ready(client: httpx.Client, server: subprocess.Popen) -> None:
    """Wait until the service answers /readyz (it is up and has warmed up its worker)."""
    deadline = time.monotonic() + _STARTUP_TIMEOUT_S
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise InputError(f"the service exited with code {server.returncode} while starting; see its output above")
        try:
            if client.get("/readyz").status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.5)
    raise InputError(f"the service was not ready (/readyz) within {_STARTUP_TIMEOUT_S:.0f} s")


def _follow_job(client: httpx.Client, job_url: str) -> dict:
    """Print the job's progress events until it finishes; return the finished job."""
    last = None
    with client.stream("GET", f"{job_url}/events", timeout=_SCAN_TIMEOUT_S) as events:
        for line in events.iter_lines():
            if not line.startswith("data:"):
                continue
            job = json.loads(line.removeprefix("data:").strip())
            progress = (job.get("status"), job.get("stage"), round(job.get("fraction", 0.0), 2))
            if progress != last:
                print(f"  job {job.get('status'):9s} {job.get('stage', ''):12s} {100 * job.get('fraction', 0):5.1f}%")
                last = progress
            if job.get("status") in ("succeeded", "failed"):
                break
    return client.get(job_url).json()


def _print_summary(scan: dict) -> None:
    summary = scan["summary"]
    print(f"\nScan {scan['scan_id']} ({scan['status']}):")
    print(f"  points: {summary['point_count']} ({summary['points_with_temperature']} with a temperature)")
    low, high = summary["bbox_min"], summary["bbox_max"]
    print("  bounding box (mm): " + ", ".join(f"{a:.1f}..{b:.1f}" for a, b in zip(low, high)))
    temperature = summary["temperature"]
    if temperature:
        percentiles = ", ".join(f"{name} {value:.1f}" for name, value in temperature["percentiles"].items())
        print(f"  temperature (deg C): min {temperature['min']:.1f}, mean {temperature['mean']:.1f}, "
              f"max {temperature['max']:.1f}; {percentiles}")


def _serve_until_interrupted(server: subprocess.Popen, data_dir: Path) -> None:
    """Wait for Ctrl-C (which the service, in the same process group, receives too) or for the service to end."""
    # a shell's background job inherits SIGINT ignored; the service stops on it regardless, so the demo must see it too
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        server.wait()
    except KeyboardInterrupt:
        try:
            server.wait(timeout=30)  # the service shuts down cleanly on the same Ctrl-C
        except subprocess.TimeoutExpired:
            pass
        print(f"\nthermofield: the service has stopped. Start it again with: thermofield serve --data-dir "
              f"{data_dir}", flush=True)
        return
    print(f"\nthermofield: the service exited with code {server.returncode}.", flush=True)


def _run(args: argparse.Namespace) -> int:
    args.data_dir.mkdir(parents=True, exist_ok=True)
    key = subprocess.run(_thermofield("apikey", "create", "--scopes", "read", "operate", "--name", "demo",
                                      "--data-dir", str(args.data_dir)),
                         capture_output=True, text=True, check=False)
    if key.returncode != 0:
        raise InputError(f"could not create an API key: {key.stderr.strip().removeprefix('thermofield: error: ')}")
    secret = key.stdout.splitlines()[0].strip()
    environment = dict(os.environ, PYTHONUNBUFFERED="1")
    server = subprocess.Popen(_thermofield("serve", "--data-dir", str(args.data_dir), "--port", str(args.port),
                                           "--gateway-port", str(args.gateway_port),
                                           "--rerun-port", str(args.rerun_port)), env=environment)
    base_url = f"http://127.0.0.1:{args.port}"
    try:
        with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {secret}"}, timeout=60) as client:
            _wait_until_ready(client, server)
            print(f"\nPOST {base_url}/v1/scans (empty body: the simulated hot part, active calibration)")
            started = time.monotonic()
            accepted = client.post("/v1/scans", json={})
            if accepted.status_code != 202:
                raise InputError(f"POST /v1/scans answered {accepted.status_code}: {accepted.text}")
            job = _follow_job(client, accepted.headers["Location"])
            if job["status"] != "succeeded":
                raise InputError(f"the scan job failed: {job.get('error')}")
            scan_id = accepted.json()["scan_id"]
            scan = client.get(f"/v1/scans/{scan_id}").json()
            print(f"  done in {time.monotonic() - started:.1f} s")
            _print_summary(scan)
            for artifact in ("field.ply", "field.rrd"):
                target = args.data_dir / f"{scan_id}-{artifact}"
                content = client.get(f"/v1/scans/{scan_id}/{artifact}").content
                with atomic_output(target) as temporary:
                    temporary.write_bytes(content)
                print(f"  saved {target}")
            print("\nWatch it in Rerun:")
            if not args.exit_after_scan:
                print(f"  live, while the service runs:  rerun --connect rerun+http://127.0.0.1:{args.rerun_port}/proxy")
            print(f"  this scan, any time:           rerun {args.data_dir / f'{scan_id}-field.rrd'}")
            print(f"  the field as a PLY (any viewer): {args.data_dir / f'{scan_id}-field.ply'}")
            if args.exit_after_scan:
                print(f"\nThe service has stopped. Start it again with: thermofield serve --data-dir {args.data_dir}")
            else:
                print(f"\nThe service keeps running on {base_url} (API docs at {base_url}/docs; scan again with "
                      f"POST /v1/scans). Ctrl-C stops it.", flush=True)
                _serve_until_interrupted(server, args.data_dir)
    finally:
        if server.poll() is None:
            server.send_signal(signal.SIGTERM)
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                server.kill()
    return 0
