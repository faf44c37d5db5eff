"""Speed of a 1280x800 structured-light capture plus one thermal frame to a 3D temperature field.

Run: .venv/bin/python benchmarks/bench_field.py [--repeats 7]

Simulates the forging station once (presets.forging_rig / forging_scene, 26-frame
Gray + phase capture, 320x256 thermal frame), warms up (the reconstruction's numba
kernels; the fusion is numpy and OpenCV), then times with the captured frames in memory:

- reconstruct: ``reconstruct_points`` (decode + triangulate, the lead's code);
- fuse: ``temperature_field`` (the normals the cloud lacks, projection, z-buffer, guard band, depth-aware
  bilinear sampling, weights, colours);
- field: both, what ``thermofield field`` computes between reading and writing;
- baseline: the naive fusion the z-buffer replaces, one ``cv2.projectPoints``
  call and ``cv2.remap`` bilinear sampling with no visibility test.

Prints median and minimum wall-clock and median process CPU milliseconds (on a
shared, oversubscribed machine CPU time is the better guide to unloaded speed),
fuse / baseline, and the load average.
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

from services.fusion.field import temperature_field
from services.fusion.fuse import ThermalView
from services.geometry.cloud import PointCloud
from services.pipeline.field import measuring_cameras

from services.simulation.presets import forging_rig, forging_scene
from services.simulation.render import CameraEffects, render_frames, render_view
from services.simulation.thermal import ThermalEffects, forging_temperatures, render_thermal
from services.structured_light.patterns import generate_sequence
from services.structured_light.reconstruct import reconstruct_points

_REMAP_WIDTH = 1024


def _naive_fusion(cloud: dict, thermal, image: np.ndarray) -> np.ndarray:
    points = np.column_stack([cloud["x"], cloud["y"], cloud["z"]]).astype(np.float64)
    rvec, _ = cv2.Rodrigues(thermal.R)
    pixels, _ = cv2.projectPoints(points, rvec, thermal.t, thermal.K, thermal.dist)
    pixels = pixels.reshape(-1, 2).astype(np.float32)
    padding = -len(pixels) % _REMAP_WIDTH  # cv2.remap maps must be under 32767 rows and columns
    maps = np.concatenate([pixels, np.full((padding, 2), -1.0, np.float32)]).reshape(-1, _REMAP_WIDTH, 2)
    sampled = cv2.remap(image, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR, borderValue=np.nan)
    return sampled.ravel()[: len(pixels)]


def _time(function, repeats: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and process CPU milliseconds of each call."""
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        function()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return np.array(wall) * 1000, np.array(cpu) * 1000


def _field(cloud, views, viewpoint, rig):
    """The fusion as `thermofield field` runs it on a fresh reconstruction: its witnesses, then the field."""
    return temperature_field(cloud, views, viewpoint, witnesses=measuring_cameras(PointCloud(dict(cloud)), rig))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()

    rig, scene = forging_rig(), forging_scene()
    camera, projector, thermal = rig.devices["camera"], rig.devices["projector"], rig.devices["thermal"]
    rng = np.random.default_rng(0)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    frames = render_frames(render_view(scene, camera, projector, supersample=1), patterns, rng,
                           CameraEffects(noise_sigma=1.0))
    image = render_thermal(scene, forging_temperatures(), thermal, ThermalEffects(), rng)
    viewpoint = camera.centre
    views = [ThermalView(thermal, image)]
    cloud = reconstruct_points(frames, sequence, camera, projector)  # warm-up (the decoder's numba kernels)
    # as `thermofield field` fuses: the unseen space of the camera that measured the cloud guards the views
    witnesses = measuring_cameras(PointCloud(dict(cloud)), rig)
    temperature_field(cloud, views, viewpoint, witnesses=witnesses)

    results = {
        "reconstruct": _time(lambda: reconstruct_points(frames, sequence, camera, projector), args.repeats),
        "fuse": _time(lambda: temperature_field(cloud, views, viewpoint, witnesses=witnesses), args.repeats),
        "fuse without the unseen space (the cloud's z-buffer alone)": _time(
            lambda: temperature_field(cloud, views, viewpoint), args.repeats),
        "field (reconstruct + fuse)": _time(
            lambda: _field(reconstruct_points(frames, sequence, camera, projector), views, viewpoint, rig),
            args.repeats),
        "baseline: naive fusion, no visibility": _time(lambda: _naive_fusion(cloud, thermal, image), args.repeats),
    }
    print(f"{len(cloud['x'])} points from {frames.shape[0]} frames of {frames.shape[2]}x{frames.shape[1]}, "
          f"thermal {thermal.width}x{thermal.height}, {args.repeats} repeats")
    print("| stage | median wall ms | min wall ms | median CPU ms |")
    print("|---|---|---|---|")
    for name, (wall, cpu) in results.items():
        print(f"| {name} | {np.median(wall):.0f} | {wall.min():.0f} | {np.median(cpu):.0f} |")
    baseline = results["baseline: naive fusion, no visibility"]
    print(f"fuse / naive baseline: {np.median(results['fuse'][0]) / np.median(baseline[0]):.2f} (wall), "
          f"{np.median(results['fuse'][1]) / np.median(baseline[1]):.2f} (CPU)")
    print(f"load average: {', '.join(f'{load:.1f}' for load in os.getloadavg())} on {os.cpu_count()} CPUs")


if __name__ == "__main__":
    main()
