"""Use case: make the first scan after a start as fast as the next.

A calibration's triangulation table takes longer to build than a scan, and a scan's first run in a process
pays for the modules it imports on first use (the PLY writer, the Rerun recording), the thread pools and
OpenCV's first calls, and the first arrays of a scan's size: glibc's malloc maps each large array afresh
(a page fault for every 4 kB) until freeing one has raised its mapping threshold. All would fall on the
first scan. :func:`warm_up` builds the active calibration's table and runs every stage of a scan once, on
a synthetic capture of a plane seen by the same rig at its full size (a warm-up on the rig scaled down to
an eighth left the first scan 0.5 s slower than the next; ``benchmarks/bench_scan_latency.py``).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from services.formats.rig import Rig
from services.formats.sequence import Sequence
from services.geometry.camera import pixel_grid, pixel_rays
from services.geometry.camera_model import CameraModel
from services.pipeline.scan import process_scan, scan_artifacts
from services.pipeline.tables import TriangulationTables
from services.structured_light.reconstruct import coded_axis

def _meeting_point(camera: CameraModel, projector: CameraModel) -> np.ndarray:
    """The point nearest to both optical axes: where the rig looks at."""
    a, b = camera.R[2], projector.R[2]  # optical axes in the world (third rows of R)
    w = camera.centre - projector.centre
    denominator = 1.0 - float(a @ b) ** 2
    s = (float(a @ b) * float(b @ w) - float(a @ w)) / denominator if denominator > 1e-9 else 500.0
    return camera.centre + max(s, 100.0) * a


def _plane_frames(camera: CameraModel, projector: CameraModel, patterns: np.ndarray,
                  rng: np.random.Generator) -> np.ndarray:
    """uint8 camera frames of the projector's ``patterns`` on a plane facing the camera where the rig looks.

    Each camera pixel's ray meets the plane at X; the frame samples the pattern at X's projector pixel
    (bilinear, ``cv2.remap``), scaled to grey levels 20..220 with 1.5 grey levels of noise. Not a rendering
    (no shading, blur or shadows: the simulator's job): the warm-up only needs decodable pixels in every stage.
    """
    origin, directions = pixel_rays(pixel_grid(camera.width, camera.height), camera.K, camera.dist, camera.R,
                                    camera.t)
    target, normal = _meeting_point(camera, projector), camera.R[2]
    points = origin + ((target - origin) @ normal / (directions @ normal))[:, None] * directions
    pixels = projector.project(points).astype(np.float32)
    maps = pixels.reshape(camera.height, camera.width, 2)
    frames = np.empty((len(patterns), camera.height, camera.width), np.uint8)
    for frame, pattern in zip(frames, patterns):  # frame by frame in float32: a scan's frames in float64 are 0.25 GB
        levels = cv2.remap(pattern, maps[..., 0], maps[..., 1], cv2.INTER_LINEAR).astype(np.float32)
        levels = 20.0 + levels * (200.0 / 255.0) + 1.5 * rng.standard_normal(levels.shape, dtype=np.float32)
        frame[:] = np.clip(np.rint(levels), 0, 255)
    return frames


def warm_up(*, rig: Rig, sequence: Sequence, tables: TriangulationTables) -> dict[str, float]:
    """Build the rig's triangulation table for ``sequence`` and run a scan of a plane through every stage.

    Returns the seconds each part took (``table``, ``stages``). A station of several heads gets every head's
    table only.
    """
    from services.structured_light.patterns import render_patterns
    from services.streaming.field import field_scene
    from services.streaming.recording import scan_recording

    seconds = {}
    start = time.perf_counter()
    if len(rig.heads) > 1:  # a station: every head's table (its heads' messages may come to any worker)
        for head in rig.heads:
            camera, projector = rig.devices[head.camera], rig.devices[head.projector]
            tables.get(camera, projector, coded_axis(sequence.coded_axes, camera, projector))
        seconds["table"] = round(time.perf_counter() - start, 3)
        return seconds
    _, camera = rig.device(None, "camera")
    _, projector = rig.device(None, "projector")
    tables.get(camera, projector, coded_axis(sequence.coded_axes, camera, projector))
    seconds["table"] = round(time.perf_counter() - start, 3)

    start = time.perf_counter()
    frames = _plane_frames(camera, projector, render_patterns(sequence), np.random.default_rng(0))
    _, thermal = rig.device(None, "thermal")
    thermal_frames = np.full((1, thermal.height, thermal.width), 900.0, np.float32)
    outcome = process_scan(frames=frames, sequence=sequence, thermal=thermal_frames, rig=rig, tables=tables)
    scan_artifacts(frames=frames, sequence=sequence, thermal=thermal_frames, outcome=outcome)
    scan_recording("warm-up", field_scene(outcome.field, rig, thermal_frames[0]))
    seconds["stages"] = round(time.perf_counter() - start, 3)
    return seconds
