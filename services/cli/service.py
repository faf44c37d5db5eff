"""``thermofield serve | api | worker | apikey``: run the service embedded or scaled out, manage API keys."""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from urllib.parse import urlsplit

from services.cli.ports import Port, require_free
from services.errors import InputError
from services.settings import Settings

_GATEWAY_START_TIMEOUT_S = 180.0


def register(subparsers: argparse._SubParsersAction) -> None:
    serve = subparsers.add_parser("serve")
    serve.add_argument("--host", help="address to bind the API to (default 127.0.0.1)")
    serve.add_argument("--port", type=int, help="API port (default 8000)")
    serve.add_argument("--data-dir", type=Path, help="database and artifacts (default ./thermofield-data)")
    serve.add_argument("--gateway-port", type=int, help="port of the simulated gateway (default 8001)")
    serve.add_argument("--rerun-port", type=int, help="port of the Rerun gRPC proxy (default 9876)")
    serve.add_argument("--rerun-web-port", type=int, help="port of Rerun's web viewer (default 9090)")
    serve.set_defaults(handler=_serve)

    api = subparsers.add_parser("api")
    api.add_argument("--host", help="bind address (default THERMOFIELD_API_HOST)")
    api.add_argument("--port", type=int, help="port (default THERMOFIELD_API_PORT)")
    api.set_defaults(handler=_api)

    worker = subparsers.add_parser("worker")
    worker.add_argument("--processes", type=int, help="worker processes (default THERMOFIELD_WORKER_PROCESSES)")
    worker.add_argument("--threads", type=int, help="jobs at once per process (default THERMOFIELD_WORKER_THREADS)")
    worker.add_argument("--check", action="store_true",
                        help="the healthcheck: exit 0 when every worker process of this host is alive (heartbeats)")
    worker.set_defaults(handler=_worker)

    maintenance = subparsers.add_parser("maintenance")
    maintenance.add_argument("--data-dir", type=Path, help="the service's data directory (embedded database)")
    maintenance.set_defaults(handler=_maintenance)

    apikey = subparsers.add_parser("apikey")
    apikey_commands = apikey.add_subparsers(dest="apikey_command", required=True, metavar="ACTION")
    create = apikey_commands.add_parser("create", help="create a key and print its secret (shown once)")
    create.add_argument("--scopes", nargs="+", required=True, metavar="SCOPE",
                        help="read, operate and/or admin, as separate words or comma-separated")
    create.add_argument("--name", default="api key", help="a label for the key")
    create.add_argument("--data-dir", type=Path, help="the service's data directory (embedded database)")
    create.set_defaults(handler=_create_api_key)
    listing = apikey_commands.add_parser("list", help="list the keys (never their secrets)")
    listing.add_argument("--data-dir", type=Path, help="the service's data directory (embedded database)")
    listing.set_defaults(handler=_list_api_keys)
    revoke = apikey_commands.add_parser("revoke", help="revoke a key by its id (it stops working within 5 s)")
    revoke.add_argument("key_id", help="the key's id, as `thermofield apikey list` shows it")
    revoke.add_argument("--data-dir", type=Path, help="the service's data directory (embedded database)")
    revoke.set_defaults(handler=_revoke_api_key)


def serve_ports(settings: Settings) -> list[Port]:
    """Every port ``thermofield serve`` binds, with the option that moves it."""
    ports = [Port(settings.api_host, settings.api_port, "the API", "--port"),
             Port("127.0.0.1", settings.gateway_port, "the simulated gateway", "--gateway-port"),
             Port(settings.rerun_host, settings.rerun_port, "the Rerun proxy", "--rerun-port")]
    if settings.rerun_web_port:
        ports.append(Port(settings.rerun_host, settings.rerun_web_port, "Rerun's web viewer", "--rerun-web-port"))
    if settings.opcua_endpoint:
        endpoint = urlsplit(settings.opcua_endpoint)
        ports.append(Port(endpoint.hostname or "0.0.0.0", endpoint.port or 4840, "the OPC UA server",
                          "THERMOFIELD_OPCUA_ENDPOINT"))
    return ports


def _settings(**overrides) -> Settings:
    return Settings(**{name: value for name, value in overrides.items() if value is not None})


def _serve(args: argparse.Namespace) -> int:
    import dramatiq

    from api.app import create_app
    from services.jobs.queue import JobQueue
    from services.runtime import build_runtime, use_runtime
    from services.streaming.proxy import RerunProxy
    from workers.broker import setup_broker

    settings = _settings(api_host=args.host, api_port=args.port, data_dir=args.data_dir, rerun_port=args.rerun_port,
                         rerun_web_port=args.rerun_web_port, gateway_port=args.gateway_port, broker_url="")
    settings = settings.model_copy(update={"gateway_url": f"http://127.0.0.1:{settings.gateway_port}"})
    require_free(serve_ports(settings))
    signal.signal(signal.SIGTERM, _exit_on_terminate)  # while starting too: the children below are stopped
    runtime = build_runtime(settings)
    use_runtime(runtime)
    _ensure_simulator_calibration(runtime)
    broker = setup_broker(settings)
    jobs = JobQueue(broker, settings.job_queue)
    worker = dramatiq.Worker(broker, worker_threads=settings.worker_threads)
    with (_GatewayProcess(settings.gateway_port) as gateway,
          RerunProxy(settings.rerun_host, settings.rerun_port, web_port=settings.rerun_web_port) as proxy,
          _maintenance_thread(runtime), _opcua_server(runtime, jobs)):
        gateway.wait_until_healthy()
        worker.start()
        runtime.tracker.recover()  # into the outbox: the API's outbox thread sends them when it starts
        print(f"thermofield: API on http://{settings.api_host}:{settings.api_port} "
              f"(docs at /docs), data in {settings.data_dir.resolve()}", flush=True)
        print(f"thermofield: Rerun: rerun --connect {proxy.url}", flush=True)
        if proxy.viewer_url:
            print(f"thermofield: Rerun in a browser: {proxy.viewer_url}", flush=True)
        try:
            _run_uvicorn(create_app(runtime, jobs), settings)
        finally:
            worker.stop()
            runtime.close_station_view()
    return 0


@contextlib.contextmanager
def _opcua_server(runtime, jobs):
    """The OPC UA server when ``THERMOFIELD_OPCUA_ENDPOINT`` is set (docs/opcua.md): its jobs go to ``jobs`` (the
    ``scan`` actor, by name) through an outbox; it follows the scans through this process's job tracker when it
    runs the jobs (``serve``), else through the workers' job states over MQTT (``api``, scaled out)."""
    settings = runtime.settings
    if not settings.opcua_endpoint:
        yield None
        return
    if settings.broker_url and not settings.mqtt_host:
        raise InputError("THERMOFIELD_OPCUA_ENDPOINT: the scaled-out API hears of the workers' results over MQTT; "
                         "set THERMOFIELD_MQTT_HOST too")
    from services.events.job_states import JobStateSubscriber
    from services.jobs.outbox import Outbox
    from services.opcua.server import OpcUaServer, ServerOptions
    from services.opcua.station import Station

    station = Station(runtime.sessions, settings.station, runtime.tracker, Outbox(runtime.sessions, jobs),
                      settings.job_queue_bound)
    with OpcUaServer(ServerOptions.from_settings(settings), station) as server:
        security = "None (unsigned, unencrypted)" if settings.opcua_security_policy == "None" else \
            f"Basic256Sha256 Sign&Encrypt, certificate {server.certificate}, trusted clients in " \
            f"{server.options.trusted_dir}"
        print(f"thermofield: OPC UA on {server.endpoint} ({security})", flush=True)
        if settings.broker_url:
            with JobStateSubscriber(settings.mqtt_host, settings.mqtt_port, settings.topic_prefix, server.notify):
                yield server
            return
        runtime.tracker.listeners.append(server.notify)
        try:
            yield server
        finally:
            runtime.tracker.listeners.remove(server.notify)


def _run_uvicorn(app, settings: Settings) -> None:
    """Serve ``app``; a SIGTERM ends it with SystemExit (after uvicorn's graceful shutdown, which re-raises
    the signal) so that the caller's clean-up runs: the embedded worker, gateway and Rerun proxy stop too."""
    from api.server import HttpLimits, serve

    signal.signal(signal.SIGTERM, _exit_on_terminate)
    serve(app, settings.api_host, settings.api_port, HttpLimits.of(settings), log_level="warning")


def _exit_on_terminate(signum, frame) -> None:
    raise SystemExit(0)


def _ensure_simulator_calibration(runtime) -> None:
    """Out of the box the station's active calibration set is the simulated rig's true calibration (the simulated
    station's of ``THERMOFIELD_SIMULATED_STATION_HEADS`` heads, when set)."""
    from sqlalchemy import select

    from services.db.models import CalibrationSet
    from services.formats.rig import rig_to_json
    from services.simulation.presets import forging_rig, station_rig

    settings = runtime.settings
    heads = settings.simulated_station_heads
    rig = station_rig(settings.simulated_station_scale, heads) if heads else forging_rig()
    with runtime.sessions.begin() as session:
        if session.scalar(select(CalibrationSet).where(CalibrationSet.station == runtime.settings.station)):
            return
        digest = runtime.store.put_bytes(rig_to_json(rig).encode())
        session.add(CalibrationSet(name="simulated rig (true calibration)", station=runtime.settings.station,
                                   rig_sha256=digest, active=True, source="simulator"))


class _GatewayProcess:
    """``thermofield gateway`` (simulated driver) as a child process of the embedded service."""

    def __init__(self, port: int) -> None:
        self.port = port

    def __enter__(self) -> _GatewayProcess:
        # In the service's process group: whatever stops the group (a kill -9 of it too) stops the gateway.
        self.process = subprocess.Popen([sys.executable, "-m", "services.cli.main", "gateway", "--driver", "simulated",
                                         "--host", "127.0.0.1", "--port", str(self.port)], stdin=subprocess.DEVNULL)
        return self

    def wait_until_healthy(self) -> None:
        """Block until the gateway answers (it traces the simulated scene first, seconds)."""
        import httpx

        deadline = time.monotonic() + _GATEWAY_START_TIMEOUT_S
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{self.port}/healthz", timeout=1.0).status_code in (200, 503):
                    return
            except httpx.HTTPError:
                pass
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise InputError(f"the simulated gateway did not start on port {self.port} "
                                 "(is the port taken? choose another with --gateway-port)")
            time.sleep(0.2)

    def __exit__(self, *exc_info: object) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)


def _api(args: argparse.Namespace) -> int:
    from api.app import create_app
    from services.jobs.queue import JobQueue, job_broker
    from services.runtime import build_runtime

    settings = _settings(api_host=args.host, api_port=args.port)
    _require_broker(settings, "api")
    runtime = build_runtime(settings)
    jobs = JobQueue(job_broker(settings), settings.job_queue)
    print(f"thermofield: API on http://{settings.api_host}:{settings.api_port}", flush=True)
    with _maintenance_thread(runtime), _opcua_server(runtime, jobs):
        _run_uvicorn(create_app(runtime, jobs), settings)
    return 0


def _maintenance_thread(runtime):
    from services.storage.retention import MaintenanceThread

    return MaintenanceThread(runtime.sessions, runtime.store, runtime.settings.retention_policy,
                             runtime.settings.maintenance_interval_s)


def _maintenance(args: argparse.Namespace) -> int:
    from services.storage.artifacts import ArtifactStore
    from services.storage.retention import run_maintenance

    settings = _settings(data_dir=args.data_dir)
    with _database(settings) as sessions:
        report = run_maintenance(sessions, ArtifactStore(settings.resolved_artifact_dir), settings.retention_policy)
    print(f"thermofield: {report.scans_expired} scans expired, raw frames of {report.raw_frames_expired} more; "
          f"{report.idempotency_records_deleted} idempotency records and {report.blobs_deleted} blobs "
          f"({report.bytes_freed / 1e6:.1f} MB) deleted")
    return 0


def _worker(args: argparse.Namespace) -> int:
    settings = _settings(worker_processes=args.processes, worker_threads=args.threads)
    if args.check:
        from workers.heartbeat import live_worker_processes

        live = live_worker_processes(settings.job_queue)
        print(f"thermofield worker: {live} of {settings.worker_processes} processes alive", flush=True)
        return 0 if live >= settings.worker_processes else 1
    from services.settings import thread_environment

    _require_broker(settings, "worker")
    command = [sys.executable, "-m", "dramatiq", "workers.main", "--use-spawn", "--queues", settings.job_queue,
               "--processes", str(settings.worker_processes), "--threads", str(settings.worker_threads)]
    # A scan takes seconds: each process takes only as many messages as it has threads, so that jobs queued
    # together spread over the processes instead of waiting in one process's prefetch.
    env = os.environ | thread_environment(settings.compute_threads) | {
        "dramatiq_queue_prefetch": str(settings.worker_threads)}
    return subprocess.run(command, env=env).returncode


def _require_broker(settings: Settings, command: str) -> None:
    if not settings.broker_url:
        raise InputError(f"`thermofield {command}` needs THERMOFIELD_BROKER_URL "
                         "(e.g. amqp://guest:guest@127.0.0.1:5672); "
                         "for a single process use `thermofield serve`")


@contextlib.contextmanager
def _database(settings: Settings):
    """Sessions of the service's database, migrated; a database that cannot be opened, read or written (a
    data directory on a read-only or full disk, a file that is not a database, a server that refuses) is
    the user's to fix: an ``InputError`` naming it (a server's URL without its password)."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import DatabaseError

    from services.db.engine import make_engine, make_sessions, migrate

    url = settings.resolved_database_url
    try:
        engine = make_engine(url, settings.database_schema)
        migrate(engine)
        yield make_sessions(engine)
    except DatabaseError as error:  # OperationalError (disk full, read-only, refused) is one
        parsed = make_url(url)
        name = parsed.database if parsed.get_backend_name() == "sqlite" else parsed.render_as_string(hide_password=True)
        full = getattr(error.orig, "sqlite_errorname", None) == "SQLITE_FULL"
        reason = f"no space left on the device holding {Path(name).parent}" if full else str(error.orig).strip()
        raise InputError(f"{name}: cannot use the database ({reason.splitlines()[0]})") from None


def _key_sessions(args: argparse.Namespace):
    return _database(_settings(data_dir=args.data_dir))


def _create_api_key(args: argparse.Namespace) -> int:
    from services.db.apikeys import create_api_key, parse_scopes

    try:
        scopes = parse_scopes(args.scopes)
    except ValueError as error:
        raise InputError(f"--scopes: {error}") from None
    with _key_sessions(args) as sessions, sessions.begin() as session:
        key, secret = create_api_key(session, args.name, scopes)
    print(secret)
    print(f"thermofield: created API key {key.id} ({args.name!r}) with scopes {' '.join(scopes)}; "
          "the secret above is shown only once", file=sys.stderr)
    return 0


def _list_api_keys(args: argparse.Namespace) -> int:
    from services.db.apikeys import list_api_keys

    with _key_sessions(args) as sessions, sessions() as session:
        keys = list_api_keys(session)
    print(f"{'id':32}  {'scopes':18}  {'created':20}  {'revoked':20}  name")
    for key in keys:
        revoked = key.revoked_at.strftime("%Y-%m-%d %H:%M:%S") if key.revoked_at else "-"
        print(f"{key.id:32}  {key.scopes:18}  {key.created_at:%Y-%m-%d %H:%M:%S}  {revoked:20}  {key.name}")
    return 0


def _revoke_api_key(args: argparse.Namespace) -> int:
    from services.db.apikeys import revoke_api_key

    with _key_sessions(args) as sessions, sessions.begin() as session:
        try:
            key = revoke_api_key(session, args.key_id)
        except KeyError:
            raise InputError(f"there is no API key {args.key_id!r} (see `thermofield apikey list`)") from None
    print(f"thermofield: revoked API key {key.id} ({key.name!r})", file=sys.stderr)
    return 0
