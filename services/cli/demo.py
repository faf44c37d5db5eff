"""``thermofield demo``: the embedded service end to end, as an MES would use it.

Starts ``thermofield serve`` (API, in-process worker, simulated gateway, SQLite, artifact directory,
Rerun proxy and web viewer), creates an API key, uploads the simulated forging's part type, scans the
hot part through ``POST /v1/scans``, follows the job's server-sent events, prints the field's summary and
the inspection's verdict, downloads ``field.ply``, ``field.rrd`` and ``report.json``, and says how to
watch it in a browser or in Rerun.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

from services.cli.ports import require_free
from services.cli.service import serve_ports
from services.errors import InputError
from services.formats.files import atomic_output
from services.settings import Settings
from services.streaming.proxy import web_viewer_url

_STARTUP_TIMEOUT_S = 180.0
_SCAN_TIMEOUT_S = 600.0
_STOP_TIMEOUT_S = 30.0
_SCOPES = ("read", "operate", "admin")


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
    parser.add_argument("--rerun-web-port", type=int, default=9090, help="Rerun web viewer port (default 9090)")
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


def _print_verdict(client: httpx.Client, scan: dict) -> None:
    """The inspection's verdict and features, or why there is none."""
    if scan.get("verdict") is None:
        return
    print(f"\nInspection against part type {scan.get('part_type_id')}: {scan['verdict']}")
    report = client.get(f"/v1/scans/{scan['scan_id']}/report.json")
    if report.status_code != 200:
        return
    for feature in report.json().get("features", []):
        if feature.get("deviation") is None:
            print(f"  {feature['name']}: {feature['verdict']} ({feature.get('error', 'not measured')})")
            continue
        print(f"  {feature['name']}: cold {feature['cold']:.3f} mm, nominal {feature['nominal']:.3f}, deviation "
              f"{feature['deviation']:+.3f} +- {feature['uncertainty']:.3f} mm: {feature['verdict']}")
    surface = report.json().get("surface") or {}
    if surface.get("verdict"):
        print(f"  surface: {surface.get('fraction_outside', 0.0):.2%} of it outside its tolerance, "
              f"{len(surface.get('defects', []))} dents or bulges reported: {surface['verdict']}")


def _part_type(client: httpx.Client, part_file: Path) -> str:
    """The simulated forging's part type, uploaded once per data directory and selected for the station."""
    name = json.loads(part_file.read_text())["name"]
    existing = [part for part in client.get("/v1/part-types").json() if part["name"] == name]
    if existing:
        part_type_id = existing[0]["part_type_id"]
        client.post(f"/v1/part-types/{part_type_id}/select").raise_for_status()
        return part_type_id
    mesh = part_file.with_name(json.loads(part_file.read_text())["nominal"])
    created = client.post("/v1/part-types", data={"select": "true"},
                          files={"part": (part_file.name, part_file.read_bytes(), "application/json"),
                                 "mesh": (mesh.name, mesh.read_bytes(), "model/stl")})
    if created.status_code != 201:
        raise InputError(f"POST /v1/part-types answered {created.status_code}: {created.text}")
    return created.json()["part_type_id"]


def _rerun_command() -> str:
    """``rerun`` as the user can type it: plain when it is on PATH, else the one installed beside this Python."""
    beside = Path(sys.executable).with_name("rerun")
    return "rerun" if shutil.which("rerun") or not beside.exists() else str(beside)


def _die_with_parent() -> None:
    """In the service's process before it runs: a SIGTERM when the demo dies, even by SIGKILL (Linux)."""
    try:
        ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (AttributeError, OSError):
        pass


def _stop(server: subprocess.Popen) -> None:
    """Stop the service as its own SIGTERM handler does (graceful, its children with it); kill it if it hangs."""
    if server.poll() is None:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(timeout=_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()


def _terminate(signum, frame) -> None:
    raise KeyboardInterrupt


def _run(args: argparse.Namespace) -> int:
    settings = Settings(api_port=args.port, gateway_port=args.gateway_port, rerun_port=args.rerun_port,
                        rerun_web_port=args.rerun_web_port, data_dir=args.data_dir)
    require_free(serve_ports(settings))  # before anything: a port in use would send the demo to another service
    # A shell's background job inherits SIGINT ignored; a Ctrl-C or a SIGTERM must stop the demo all the same.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _terminate)
    args.data_dir.mkdir(parents=True, exist_ok=True)
    key = subprocess.run(_thermofield("apikey", "create", "--scopes", *_SCOPES, "--name", "demo",
                                      "--data-dir", str(args.data_dir)),
                         capture_output=True, text=True, check=False)
    if key.returncode != 0:
        raise InputError(f"could not create an API key: {key.stderr.strip().removeprefix('thermofield: error: ')}")
    secret = key.stdout.splitlines()[0].strip()
    environment = dict(os.environ, PYTHONUNBUFFERED="1")
    # The service runs in a session of its own: the demo alone hears the terminal's Ctrl-C and stops it once.
    server = subprocess.Popen(_thermofield("serve", "--data-dir", str(args.data_dir), "--port", str(args.port),
                                           "--gateway-port", str(args.gateway_port),
                                           "--rerun-port", str(args.rerun_port),
                                           "--rerun-web-port", str(args.rerun_web_port)),
                              env=environment, stdin=subprocess.DEVNULL, start_new_session=True,
                              preexec_fn=_die_with_parent)
    base_url = f"http://127.0.0.1:{args.port}"
    try:
        with httpx.Client(base_url=base_url, headers={"Authorization": f"Bearer {secret}"}, timeout=60) as client:
            _wait_until_ready(client, server)
            print(f"\nAPI key for this demo (scopes {', '.join(_SCOPES)}; more with `thermofield apikey create "
                  f"--scopes read operate --data-dir {args.data_dir}`):\n  {secret}")
            # the simulated forging's cold nominal and part file, made as the tests make them
            from services.simulation.hot_part import write_forging_part

            part_file = write_forging_part(args.data_dir / "forging-part")
            part_type_id = _part_type(client, part_file)
            print(f"\nPart type {part_type_id}: the simulated forging, cold ({part_file}), selected for the station")
            print(f"\nPOST {base_url}/v1/scans (empty body: the simulated hot part, the active calibration and the "
                  "selected part type)")
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
            _print_verdict(client, scan)
            for artifact in ("field.ply", "field.rrd", "report.json"):
                response = client.get(f"/v1/scans/{scan_id}/{artifact}")
                if response.status_code != 200:
                    continue
                target = args.data_dir / f"{scan_id}-{artifact}"
                with atomic_output(target) as temporary:
                    temporary.write_bytes(response.content)
                print(f"  saved {target}")
            rerun = _rerun_command()
            print("\nWatch it:")
            if not args.exit_after_scan:
                print(f"  in a browser, live:              "
                      f"{web_viewer_url('127.0.0.1', args.rerun_web_port, args.rerun_port)}")
                print(f"  in Rerun, live:                  {rerun} --connect "
                      f"rerun+http://127.0.0.1:{args.rerun_port}/proxy")
            print(f"  this scan in Rerun, any time:    {rerun} {args.data_dir / f'{scan_id}-field.rrd'}")
            print(f"  the field as a PLY (any viewer): {args.data_dir / f'{scan_id}-field.ply'}")
            if args.exit_after_scan:
                _stop(server)
                print(f"\nThe service has stopped. Start it again with: thermofield serve --data-dir {args.data_dir}")
                return 0
            print(f"\nThe service keeps running on {base_url} (API docs at {base_url}/docs). Scan again:\n"
                  f"  curl -X POST -H 'Authorization: Bearer {secret}' -H 'Content-Type: application/json' "
                  f"-d '{{}}' {base_url}/v1/scans\nCtrl-C stops it.", flush=True)
            server.wait()
            print(f"\nthermofield: the service exited with code {server.returncode}.", flush=True)
            return 1
    except KeyboardInterrupt:
        _stop(server)
        print(f"\nthermofield: the service has stopped. Start it again with: thermofield serve --data-dir "
              f"{args.data_dir}", flush=True)
        return 130
    finally:
        _stop(server)
