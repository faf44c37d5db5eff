"""OPC UA result latency: from a scan's result stored to the ResultReady event at an MES.

Run by hand (not a test):

    .venv/bin/python benchmarks/bench_opcua.py [--mode embedded|scaled-out] [--runs 5] [--scans 20]

Starts the station's OPC UA server (Basic256Sha256 Sign&Encrypt, an API key as the MES's password) on a fresh
database (SQLite embedded, a fresh PostgreSQL schema scaled out) and connects an asyncua MES that subscribes to
ResultReady with a publishing interval of ``--interval-ms`` (the server sends its queued events every this
often: an event waits half of it on average). Each scan is a queued scan job (as
StartSingleJob makes it) that a worker's job tracker runs as the scan actor's bookkeeping does: started, capture,
reconstruct, then ``succeed``, the commit that records the job's result (the field's artifacts already stored,
its summary and verdict) on the scan. The latency is from just before that commit to the MES's event handler
receiving the scan's ResultReady. Embedded, the tracker is the server process's (``thermofield serve``: the
event follows the tracker's listener); scaled out, the worker's tracker publishes the job state on the local
MQTT broker and the server hears it through its subscriber, as ``thermofield api`` does.

The baseline, measured in the same run, is the commit itself (``succeed`` returning): the ratio says what the
OPC UA path adds on top of storing the result. Each run reports its median; the summary gives the median over
the runs, the 95th percentile and the worst of all scans. Server, MES and worker share this one process (three
threads), so the figures include their contention for the interpreter.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from services.db.apikeys import create_api_key  # noqa: E402
from services.db.engine import make_engine, make_sessions, migrate  # noqa: E402
from services.db.models import CalibrationSet, PartType  # noqa: E402
from services.events.job_states import JobStateSubscriber  # noqa: E402
from services.events.mqtt import EventPublisher  # noqa: E402
from services.jobs.tracker import JobTracker  # noqa: E402
from services.opcua.server import OpcUaServer, ServerOptions  # noqa: E402
from services.opcua.station import Station  # noqa: E402
from tests.opcua.mes import Mes, client_certificate, value  # noqa: E402

POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
STATION = "station1"


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class _MesThread:
    """The MES on its own thread and event loop, subscribed to ResultReady."""

    def __init__(self, endpoint: str, key: str, certificate, interval_ms: float) -> None:
        self.endpoint, self.key, self.certificate, self.interval_ms = endpoint, key, certificate, interval_ms
        self.mes: Mes | None = None
        self.ready, self.stop = threading.Event(), threading.Event()
        self.thread = threading.Thread(target=lambda: asyncio.run(self._run()), daemon=True)
        self.thread.start()
        if not self.ready.wait(60):
            raise RuntimeError("the MES did not connect")

    async def _run(self) -> None:
        async with Mes(self.endpoint, self.key, self.certificate) as mes:
            await mes.subscribe("ResultReadyEventType", interval_ms=self.interval_ms)
            self.mes = mes
            self.ready.set()
            while not self.stop.is_set():
                await asyncio.sleep(0.05)

    def arrival(self, scan_id: str, timeout_s: float = 10.0) -> float | None:
        """When the scan's ResultReady reached the MES's handler (perf_counter), None if it did not."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for event, at in zip(list(self.mes.events), list(self.mes.event_times)):
                result = value(event, "ResultId")
                if result is not None and getattr(result, "Id", None) == scan_id:
                    return at
            time.sleep(0.001)
        return None


def run(mode: str, scans: int, interval_ms: float, directory: Path) -> tuple[list[float], list[float]]:
    """One run: each scan's latency to the MES and its commit's duration, in ms."""
    if mode == "embedded":
        engine = make_engine(f"sqlite:///{directory / 'service.db'}")
        schema = None
    else:
        schema = f"tf_bench_{uuid.uuid4().hex[:10]}"
        engine = make_engine(POSTGRES_URL, schema)
    migrate(engine)
    sessions = make_sessions(engine)
    with sessions.begin() as session:
        session.add_all([CalibrationSet(id="c1", name="rig", station=STATION, source="upload", active=True,
                                        rig_sha256="r" * 64),
                         PartType(id="billet", name="billet-90", station=STATION, material="carbon-steel",
                                  part_sha256="a" * 64, mesh_sha256="b" * 64, selected=True)])
        _, key = create_api_key(session, "bench MES", ["read"])
    prefix = f"bench-{uuid.uuid4().hex[:8]}/{STATION}"
    worker = JobTracker(sessions, EventPublisher("127.0.0.1", 1883, prefix) if mode == "scaled-out" else None)
    api = JobTracker(sessions, EventPublisher("127.0.0.1", 1883, prefix)) if mode == "scaled-out" else worker
    station = Station(sessions, STATION, api, None)
    options = ServerOptions(f"opc.tcp://127.0.0.1:{_free_port()}/thermofield", pki_dir=directory / "pki")
    latencies, commits = [], []
    try:
        with OpcUaServer(options, station) as server:
            subscriber = None
            if mode == "scaled-out":
                subscriber = JobStateSubscriber("127.0.0.1", 1883, prefix, server.notify).__enter__()
                subscriber.subscribed.wait(20)
            else:
                worker.listeners.append(server.notify)
            certificate = asyncio.run(client_certificate(directory / "mes", options.trusted_dir))
            mes = _MesThread(options.endpoint, key, certificate, interval_ms)
            try:
                recipe = station.find_recipe("billet", None)
                for index in range(scans):
                    job = station.start_scan(part_id=f"part-{index}", recipe=recipe, meas_id="bench", job_id=None)
                    scan_id = job.params["scan_id"]
                    worker.start(job.id, "bench-worker:1")
                    worker.progress(job.id, "capture", 0.05)
                    worker.progress(job.id, "reconstruct", 0.3)
                    time.sleep(0.05)  # the processing: the states before the result have reached the server
                    started = time.perf_counter()
                    worker.succeed(job.id, {"verdict": "OK", "features": [], "stage_seconds": {"capture": 1.0}})
                    committed = time.perf_counter()
                    arrived = mes.arrival(scan_id)
                    if arrived is None:
                        raise RuntimeError(f"no ResultReady for scan {scan_id}")
                    latencies.append(1000 * (arrived - started))
                    commits.append(1000 * (committed - started))
            finally:
                mes.stop.set()
                mes.thread.join(10)
                if subscriber is not None:
                    subscriber.__exit__(None, None, None)
    finally:
        for tracker in {worker, api}:
            if tracker.publisher is not None:
                tracker.publisher.close()
        engine.dispose()
        if schema is not None:
            from sqlalchemy import text

            with make_engine(POSTGRES_URL).begin() as connection:
                connection.execute(text(f"DROP SCHEMA {schema} CASCADE"))
    return latencies, commits


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=("embedded", "scaled-out"), default="embedded")
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--scans", type=int, default=20)
    parser.add_argument("--interval-ms", type=float, default=20.0,
                        help="the MES's publishing interval: the server sends what it has every this often")
    args = parser.parse_args()
    medians, every, commit_medians = [], [], []
    for number in range(args.runs):
        with tempfile.TemporaryDirectory() as directory:
            latencies, commits = run(args.mode, args.scans, args.interval_ms, Path(directory))
        medians.append(statistics.median(latencies))
        commit_medians.append(statistics.median(commits))
        every.extend(latencies)
        print(f"run {number + 1}: median {medians[-1]:.1f} ms (commit {commit_medians[-1]:.1f} ms), "
              f"worst {max(latencies):.1f} ms over {len(latencies)} scans", flush=True)
    every.sort()
    median = statistics.median(medians)
    print(f"\n{args.mode}: result stored -> ResultReady at the MES, {args.runs} runs x {args.scans} scans, "
          f"publishing interval {args.interval_ms:g} ms")
    print(f"| median of the runs' medians | 95th percentile | worst | commit alone (median) | ratio |")
    print(f"|---|---|---|---|---|")
    print(f"| {median:.1f} ms | {every[int(0.95 * (len(every) - 1))]:.1f} ms | {every[-1]:.1f} ms "
          f"| {statistics.median(commit_medians):.1f} ms | {median / statistics.median(commit_medians):.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
