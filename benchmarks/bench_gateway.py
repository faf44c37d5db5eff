"""Capture speed of the simulated gateway at full size, against rendering the same frames directly.

    .venv/bin/python benchmarks/bench_gateway.py [--repeats 5]

Baseline: ``render_frames`` of every pattern (what the simulated camera must do
anyway). Measured in the same run: ``Station.capture`` (show, grab, thermal frame) and
the HTTP capture through ``GatewayClient`` (plus ``.npz`` transfer), and
``scan_recording`` of a 500 000-point field. Prints medians and ratios to the baseline.
"""

from __future__ import annotations

import argparse
import socket
import statistics
import threading
import time

import numpy as np
import uvicorn

from device_gateway.app import create_app
from device_gateway.client import GatewayClient
from device_gateway.drivers.simulated import SimulatedStation
from device_gateway.station import Station
from services.simulation.render import render_frames
from services.streaming.field import field_scene
from services.streaming.recording import scan_recording
from services.structured_light.patterns import generate_sequence


def _seconds(action) -> float:
    started = time.perf_counter()
    action()
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()

    simulated = SimulatedStation()
    station = Station(simulated.camera, simulated.thermal, simulated.projector)
    started = time.perf_counter()
    station.open()
    print(f"open (trace the scene once): {time.perf_counter() - started:.1f} s")
    projector = simulated.rig.devices["projector"]
    sequence, patterns = generate_sequence(projector.width, projector.height)
    rng = np.random.default_rng(0)
    options = simulated.options

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(create_app(station, sequence, patterns), host="127.0.0.1", port=port,
                                           log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.05)
    # Interleaved, so that load from other processes on the machine hits all three alike.
    timings: dict[str, list[float]] = {"baseline": [], "station": [], "http": []}
    with GatewayClient(f"http://127.0.0.1:{port}") as client:
        for _ in range(args.repeats):
            timings["baseline"].append(_seconds(lambda: render_frames(
                simulated.view(), patterns, rng, options.camera_effects, options.projector_effects)))
            timings["station"].append(_seconds(lambda: station.capture(sequence, patterns)))
            timings["http"].append(_seconds(client.capture))
    server.should_exit = True
    thread.join()
    baseline, in_process, over_http = (statistics.median(timings[name]) for name in ("baseline", "station", "http"))

    count = 500_000
    field = {axis: rng.uniform(-100, 100, count).astype(np.float32) for axis in "xyz"}
    field["temperature"] = rng.uniform(900, 1100, count).astype(np.float32)
    thermal = simulated.clean_thermal()
    recording = statistics.median(_seconds(lambda: scan_recording("bench", field_scene(field, simulated.rig, thermal)))
                                  for _ in range(args.repeats))

    size = f"{len(patterns)} patterns, camera {simulated.camera.info.width}x{simulated.camera.info.height}"
    print(f"medians of {args.repeats} runs ({size}):")
    print(f"  render_frames alone (baseline): {baseline:.3f} s")
    print(f"  Station.capture:                {in_process:.3f} s  ({in_process / baseline:.2f}x baseline)")
    print(f"  HTTP capture (client):          {over_http:.3f} s  ({over_http / baseline:.2f}x baseline)")
    print(f"  scan_recording, 500k points:    {recording:.3f} s")


if __name__ == "__main__":
    main()
