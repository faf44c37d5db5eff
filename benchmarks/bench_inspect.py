"""Speed of ``inspect_field`` on a 500k-point temperature field of a hot billet.

Run: .venv/bin/python benchmarks/bench_inspect.py [--repeats 7] [--scale 2.8]

Simulates the 90 mm carbon-steel billet at 1000 degC (hot_part.billet_pose) before the forging rig
at ``--scale`` times its resolution (2.8: a 3584x2240 camera, about 520 000 points of the part),
prepares the part once (mesh, distance queries, nominal feature fits: what the service keeps per
part type), then times, in process:

- prepare: ``prepare_part`` and the nominal's distance grid, which the first inspection builds (once
  per part type, not per scan);
- inspect: ``inspect_field`` with the prepared part (cold-equivalent geometry, alignment, fits,
  deviation of every point, defects, verdicts);
- baseline: one Open3D closest-point query of every point against the nominal mesh, the floor
  of any per-point deviation map.

Prints median and minimum wall-clock and median process CPU milliseconds and the load average.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from services.formats.part import load_part
from services.inspection.inspect import inspect_field, prepare_part
from services.simulation.hot_part import HotPart, billet_pose, simulated_field, write_billet_part
from services.simulation.presets import forging_rig
from services.simulation.thermal import SurfaceTemperature


def _time(function, repeats: int) -> tuple[np.ndarray, np.ndarray]:
    wall, cpu = [], []
    for _ in range(repeats):
        start_wall, start_cpu = time.perf_counter(), time.process_time()
        function()
        wall.append(time.perf_counter() - start_wall)
        cpu.append(time.process_time() - start_cpu)
    return np.asarray(wall) * 1000, np.asarray(cpu) * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--scale", type=float, default=2.8)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as directory:
        part = load_part(write_billet_part(directory))
    rig = forging_rig(args.scale)
    hot = HotPart(part.vertices, part.triangles, part.material, SurfaceTemperature(base=1000.0), pose=billet_pose())
    devices = rig.devices
    field, _ = simulated_field(hot, devices["camera"], devices["projector"], devices["thermal"],
                               np.random.default_rng(0))
    prepared = prepare_part(part)
    inspect_field(field=field, part=prepared)  # warm-up
    points = np.column_stack([field["x"], field["y"], field["z"]]).astype(np.float64)
    results = {
        "prepare (once per part type)": _time(lambda: prepare_part(part).nominal.grid, max(1, args.repeats // 3)),
        "inspect": _time(lambda: inspect_field(field=field, part=prepared), args.repeats),
        "baseline: closest points of every point": _time(lambda: prepared.nominal.closest(points), args.repeats),
    }
    print(f"{len(points)} points, camera {devices['camera'].width}x{devices['camera'].height}, "
          f"{len(part.triangles)} nominal triangles, {args.repeats} repeats")
    print("| stage | median wall ms | min wall ms | median CPU ms |")
    print("|---|---|---|---|")
    for name, (wall, cpu) in results.items():
        print(f"| {name} | {np.median(wall):.0f} | {wall.min():.0f} | {np.median(cpu):.0f} |")
    inspect, baseline = results["inspect"], results["baseline: closest points of every point"]
    print(f"inspect / baseline: {np.median(inspect[0]) / np.median(baseline[0]):.2f} (wall)")
    print(f"load average: {', '.join(f'{load:.1f}' for load in os.getloadavg())} on {os.cpu_count()} CPUs")


if __name__ == "__main__":
    main()
