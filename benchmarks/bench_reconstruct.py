"""Speed and memory of decode + triangulate, beside a plain vectorised numpy decoder on the same frames.

Run by hand (not a test; machines are shared and noisy):

    .venv/bin/python benchmarks/bench_reconstruct.py [--repeats 15] [--out docs/benchmark-reconstruct.md]

Captures are rendered once by the simulator (the forging station's part at 1280x800, and the same
station with 1920x1080 camera and projector). The baseline decodes the same frames in plain vectorised
numpy and triangulates by the same per-calibration table, also in plain numpy; the table is built once,
outside the timed region, for both. Ours and the baseline run in turn, so that load changes on a shared
machine hit both alike. Peak memory is the largest traced allocation (``tracemalloc``) during one scan,
beside the size of the input frames. Last, the full scan's stages are timed back to back, to show where its
time goes.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np

from services.geometry.camera_model import CameraModel
from services.simulation.presets import forging_rig, forging_scene
from services.simulation.render import CameraEffects, ProjectorEffects, render_frames, render_view
from services.structured_light.decode import decode
from services.structured_light.patterns import generate_sequence
from services.structured_light.reconstruct import (
    _MIN_MODULATION_OF_FULL_SCALE,
    _MIN_QUALITY,
    _cloud,
    _coordinate_step_limit,
    _refined_coordinates,
    reconstruct_points,
    remove_speckles,
)
from services.structured_light.triangulate import TriangulationTable, triangulate_map, triangulation_table


def _scaled(device: CameraModel, width: int, height: int) -> CameraModel:
    scale = width / device.width
    K = device.K.copy()
    K[:2] *= scale
    K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
    return device.replace(**{"width": width, "height": height, "K": K.tolist()})


def _capture(width: int, height: int):
    rig = forging_rig()
    camera = _scaled(rig.devices["camera"], width, height)
    projector = _scaled(rig.devices["projector"], width, height)
    sequence, patterns = generate_sequence(projector.width, projector.height)
    view = render_view(forging_scene(), camera, projector, supersample=1)
    frames = render_frames(view, patterns, np.random.default_rng(0),
                           CameraEffects(noise_sigma=1.5, blur_sigma=0.7), ProjectorEffects(blur_sigma=0.8))
    return camera, projector, sequence, frames


def numpy_decode(frames: np.ndarray, sequence) -> np.ndarray:
    """The baseline: a plain vectorised numpy decoder of complementary Gray code + N-step phase shift.

    Threshold each Gray plane against its inverse, convert Gray to binary by cumulative XOR, take the
    wrapped phase from the arctangent of the sine and cosine sums, and unwrap it with the stripe index
    (nearest period to the Gray-code estimate). Shadowed pixels (white - black below 10 grey levels)
    are NaN.
    """
    f = frames.astype(np.float32)
    valid = (f[sequence.white_index] - f[sequence.black_index]) > 10
    planes = sequence.gray_planes("x")[::-1]  # most significant first
    binary = np.zeros(frames.shape[1:], dtype=np.int32)
    bit_value = np.zeros(frames.shape[1:], dtype=np.int32)
    for plane in planes:
        bit = (f[plane.frame] > f[plane.complement]).astype(np.int32)
        bit_value ^= bit
        binary = (binary << 1) | bit_value
    finest = planes[-1].bit
    gray_estimate = (binary + 0.5) * (1 << finest) - 0.5
    group = sequence.phase_groups("x")[0]
    deltas = 2 * np.pi * np.arange(len(group.frames)) / len(group.frames)
    stack = f[list(group.frames)]
    sine = np.tensordot(np.sin(deltas).astype(np.float32), stack, axes=1)
    cosine = np.tensordot(np.cos(deltas).astype(np.float32), stack, axes=1)
    wrapped = np.mod(np.arctan2(sine, cosine), 2 * np.pi) * (group.period / (2 * np.pi))
    coordinate = wrapped + group.period * np.round((gray_estimate - wrapped) / group.period)
    return np.where(valid, coordinate, np.nan).astype(np.float32)


def numpy_triangulate(table: TriangulationTable, coordinate: np.ndarray) -> np.ndarray:
    """The baseline's triangulation: the same table lookup as ``triangulate_map``, in plain vectorised numpy
    over the decoded pixels (the table is built once per calibration, outside the timed region, for both)."""
    index = np.flatnonzero(np.isfinite(coordinate))
    pixel = table.pixel_geometry.reshape(-1, 3)[index].astype(np.float64)
    fq, fc = pixel[:, 0], coordinate.ravel()[index].astype(np.float64) + 1.0
    inside = (fq >= 0) & (fq < table.exact_cells.shape[1]) & (fc >= 0) & (fc < table.exact_cells.shape[0])
    q, c = np.where(inside, fq, 0).astype(np.int64), np.where(inside, fc, 0).astype(np.int64)
    wq, wc = fq - q, fc - c
    offsets = table.line_offsets
    offset = ((1 - wc) * ((1 - wq) * offsets[c, q] + wq * offsets[c, q + 1])
              + wc * ((1 - wq) * offsets[c + 1, q] + wq * offsets[c + 1, q + 1]))
    n = (fc - 1.0 - table.projector_K[0, 2]) / table.projector_K[0, 0] + offset
    rays = np.column_stack([pixel[:, 1:], np.ones(len(pixel))])
    d = rays @ table.rotation.T
    o = table.origin
    s = (n * o[2] - o[0]) / (d[:, 0] - n * d[:, 2])
    s = np.where(inside & (s > 0), s, np.nan)
    return (table.centre_world + s[:, None] * (rays @ table.camera_to_world.T)).astype(np.float32)


def numpy_reconstruct(frames, sequence, table: TriangulationTable) -> np.ndarray:
    return numpy_triangulate(table, numpy_decode(frames, sequence))


_SETTLE_S = 0.3  # OpenBLAS and OpenMP worker threads spin for up to ~0.1 s after a call


def _interleaved_times_ms(functions: dict, repeats: int) -> dict[str, list[float]]:
    """Wall times of each function, run in turn so that a change in the machine's load hits all alike,
    with a pause before each run so that the previous one's spinning worker threads do not steal a core."""
    for function in functions.values():
        function()  # warm-up: numba compilation and caches
    times = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            time.sleep(_SETTLE_S)
            start = time.perf_counter()
            function()
            times[name].append(1000 * (time.perf_counter() - start))
    return times


def _stage_medians_ms(frames, sequence, camera, projector, table, repeats: int) -> dict[str, float]:
    """Median time of each stage of ``reconstruct_points``, the stages run back to back as it runs them."""
    axis = table.axis
    decoded = coordinates = kept = points_map = cloud = None

    def decode_stage():
        nonlocal decoded
        decoded = decode(frames, sequence, min_quality=_MIN_QUALITY, edge_margin=0,
                         min_modulation=_MIN_MODULATION_OF_FULL_SCALE * np.iinfo(frames.dtype).max)

    def refine_stage():
        nonlocal coordinates
        coordinates = _refined_coordinates(decoded, sequence, axis)

    def speckle_stage():
        nonlocal kept
        kept = remove_speckles(coordinates, _coordinate_step_limit(sequence, axis))

    def triangulate_stage():
        nonlocal points_map
        points_map = triangulate_map(table, kept)

    def cloud_stage():
        nonlocal cloud
        cloud = _cloud(points_map, table.centre_world, kept, decoded)

    stages = {"decode": decode_stage,
              "blur estimate, outline correction, noise estimate, weak-signal refinement": refine_stage,
              "speckle filter": speckle_stage, "triangulation": triangulate_stage, "cloud with normals": cloud_stage}
    times = {name: [] for name in stages}
    for repeat in range(repeats + 1):
        for name, stage in stages.items():
            start = time.perf_counter()
            stage()
            if repeat > 0:  # the first pass is the warm-up
                times[name].append(1000 * (time.perf_counter() - start))
    scan = reconstruct_points(frames, sequence, camera, projector, table=table)
    if not all(np.array_equal(cloud[name], scan[name], equal_nan=True) for name in scan):
        raise RuntimeError("The timed stages no longer give reconstruct_points' cloud; update _stage_medians_ms.")
    return {name: statistics.median(values) for name, values in times.items()}


def _peak_mb(function) -> float:
    tracemalloc.start()
    function()
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def _cpu_jiffies() -> tuple[int, int]:
    """Total and stolen CPU time so far (Linux /proc/stat): steal is time the hypervisor gave another guest."""
    fields = [int(value) for value in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    return sum(fields), fields[7]


def run(repeats: int) -> list[dict]:
    rows = []
    for width, height in ((1280, 800), (1920, 1080)):
        camera, projector, sequence, frames = _capture(width, height)
        start = time.perf_counter()
        table = triangulation_table(camera, projector, "x")
        table_s = time.perf_counter() - start
        table_mb = sum(getattr(table, name).nbytes for name in ("pixel_geometry", "line_offsets", "exact_cells")) / 2**20
        scan = lambda: reconstruct_points(frames, sequence, camera, projector, table=table)  # noqa: E731
        decode_triangulate = lambda: triangulate_map(table, decode(frames, sequence).projector_x)  # noqa: E731
        baseline = lambda: numpy_reconstruct(frames, sequence, table)  # noqa: E731
        total_before, steal_before = _cpu_jiffies()
        times = _interleaved_times_ms({"scan": scan, "decode_triangulate": decode_triangulate, "baseline": baseline},
                                      repeats)
        total_after, steal_after = _cpu_jiffies()
        row = {
            "size": f"{width}x{height}", "frames": len(frames), "input_mb": frames.nbytes / 2**20,
            "points": len(scan()["x"]), "baseline_points": len(baseline()),
            "scan_ms": statistics.median(times["scan"]),
            "decode_triangulate_ms": statistics.median(times["decode_triangulate"]),
            "baseline_ms": statistics.median(times["baseline"]), "baseline_fastest_ms": min(times["baseline"]),
            "scan_peak_mb": _peak_mb(scan), "baseline_peak_mb": _peak_mb(baseline),
            "table_s": table_s, "table_mb": table_mb,
            "steal": (steal_after - steal_before) / max(1, total_after - total_before),
            "stages": _stage_medians_ms(frames, sequence, camera, projector, table, repeats),
        }
        rows.append(row)
        print(row, flush=True)
    return rows


def _coding() -> str:
    sequence, _ = generate_sequence(1280, 800)
    group = sequence.phase_groups("x")[0]
    return f"complementary Gray code + {len(group.frames)}-step phase shift of period {group.period:g} px"


def report(rows: list[dict], repeats: int) -> str:
    lines = ["# Benchmark: decode + triangulate", "",
             f"Command: `.venv/bin/python benchmarks/bench_reconstruct.py --repeats {repeats}` "
             f"(medians of {repeats} runs after a warm-up, the three run in turn with a {_SETTLE_S} s pause "
             f"before each; {platform.processor() or platform.machine()}, {os.cpu_count()} cores, numba "
             f"threads {os.environ.get('NUMBA_NUM_THREADS', 'default')}).", "",
             f"- **Baseline**: a plain vectorised numpy decoder of the same {_coding()} (`numpy_decode` in "
             "the script) on the same frames, followed by the table triangulation written in plain vectorised "
             "numpy (`numpy_triangulate`).",
             "- **Decode + triangulate**: the same work by thermofield's kernels: `decode` and `triangulate_map`.",
             "- **Full scan**: `reconstruct_points`, which also corrects the outline's blur bias, refines "
             "weak-signal pixels, removes speckles and computes normals (docs/structured-light.md); the "
             "baseline does none of this.",
             "- The baseline's run times are bimodal on this machine (about 150 ms, or two to three times that in "
             "some runs), so its fastest run is given beside the median, and the full scan's speed-up against it "
             "in brackets: the conservative figure.",
             "- All use the triangulation table, built once per calibration outside the timed region (build "
             "time and size in a column). CPU stolen: the share of the machine's CPU time the hypervisor gave "
             "to other guests during the timed runs (`/proc/stat`); parallel code loses more to it than the "
             "mostly single-threaded baseline. Memory: peak traced allocation during one scan "
             "(`tracemalloc`; numba's own allocations go through numpy and are counted), beside the size of "
             "the input frames.", "",
             "| capture | frames | input MB | points: full scan (baseline) | baseline ms (fastest) | "
             "decode + triangulate ms | speed-up | full scan ms | speed-up (against the fastest baseline) | "
             "full scan Mpoints/s | full scan peak MB | peak / input | baseline peak MB | table: build s, MB | "
             "CPU stolen |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['size']} | {r['frames']} | {r['input_mb']:.1f} | {r['points']} ({r['baseline_points']}) | "
            f"{r['baseline_ms']:.1f} ({r['baseline_fastest_ms']:.1f}) | {r['decode_triangulate_ms']:.1f} | "
            f"{r['baseline_ms'] / r['decode_triangulate_ms']:.1f}x | {r['scan_ms']:.1f} | "
            f"{r['baseline_ms'] / r['scan_ms']:.1f}x ({r['baseline_fastest_ms'] / r['scan_ms']:.1f}x) | "
            f"{r['points'] / r['scan_ms'] / 1000:.1f} | "
            f"{r['scan_peak_mb']:.1f} | {r['scan_peak_mb'] / r['input_mb']:.2f} | {r['baseline_peak_mb']:.1f} | "
            f"{r['table_s']:.2f}, {r['table_mb']:.1f} | {100 * r['steal']:.0f} % |")
    lines += ["", "Where the full scan's time goes: the median of each stage of `reconstruct_points`, the stages run "
              "back to back without the pause (so without the wake-up of idle threads that the pause costs the "
              "scan above).", "",
              "| stage | " + " | ".join(f"{r['size']} ms" for r in rows) + " |",
              "|---|" + "---|" * len(rows)]
    for stage in rows[0]["stages"]:
        lines.append(f"| {stage} | " + " | ".join(f"{r['stages'][stage]:.1f}" for r in rows) + " |")
    lines.append("| sum | " + " | ".join(f"{sum(r['stages'].values()):.1f}" for r in rows) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description="decode + triangulate benchmark")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--out", type=Path, default=Path("docs/benchmark-reconstruct.md"))
    args = parser.parse_args()
    text = report(run(args.repeats), args.repeats)
    args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
