"""Use case: make the first scan after a start as fast as the next.

numba compiles (or loads from its cache) each kernel on its first call in a process, and a calibration's
triangulation table takes longer to build than a scan; both would fall on the first scan. :func:`warm_up`
builds the active calibration's table and runs every kernel of a scan once, on a small simulated capture
of a plane seen by the same rig scaled down (kernels are compiled per argument type, not per size).
"""

from __future__ import annotations

import time

import numpy as np

from services.formats.rig import Rig
from services.formats.sequence import Sequence
from services.geometry.camera_model import CameraModel
from services.pipeline.scan import process_scan, scan_artifacts
from services.pipeline.tables import TriangulationTables
from services.structured_light.reconstruct import coded_axis

_SCALE = 8  # the small rig's devices have an eighth of the pixels along each side


def _scaled(device: CameraModel, factor: int) -> CameraModel:
    K = np.array(device.K)
    K[:2] /= factor
    K[:2, 2] = (device.K[:2, 2] + 0.5) / factor - 0.5
    return device.replace(width=max(device.width // factor, 8), height=max(device.height // factor, 8), K=K)


def _meeting_point(camera: CameraModel, projector: CameraModel) -> np.ndarray:
    """The point nearest to both optical axes: where the rig looks at."""
    a, b = camera.R[2], projector.R[2]  # optical axes in the world (third rows of R)
    w = camera.centre - projector.centre
    denominator = 1.0 - float(a @ b) ** 2
    s = (float(a @ b) * float(b @ w) - float(a @ w)) / denominator if denominator > 1e-9 else 500.0
    return camera.centre + max(s, 100.0) * a


def warm_up(*, rig: Rig, sequence: Sequence, tables: TriangulationTables) -> dict[str, float]:
    """Build the rig's triangulation table for ``sequence`` and run a small scan through every kernel.

    Returns the seconds each part took (``table``, ``kernels``).
    """
    from services.simulation.render import render_frames, render_view
    from services.simulation.scene import Plane, Scene
    from services.structured_light.patterns import generate_sequence
    from services.streaming.field import field_scene
    from services.streaming.recording import scan_recording

    seconds = {}
    start = time.perf_counter()
    _, camera = rig.device(None, "camera")
    _, projector = rig.device(None, "projector")
    tables.get(camera, projector, coded_axis(sequence.coded_axes, camera, projector))
    seconds["table"] = round(time.perf_counter() - start, 3)

    start = time.perf_counter()
    small = Rig({name: _scaled(device, _SCALE) for name, device in rig.devices.items()})
    _, small_camera = small.device(None, "camera")
    _, small_projector = small.device(None, "projector")
    centre = _meeting_point(small_camera, small_projector)
    normal = -small_camera.R[2]
    u_axis = np.cross(normal, [0.0, 1.0, 0.0])
    u_axis = u_axis / np.linalg.norm(u_axis) if np.linalg.norm(u_axis) > 1e-6 else np.array([1.0, 0.0, 0.0])
    scene = Scene(surfaces=[Plane(center=centre.tolist(), normal=normal.tolist(), u_axis=u_axis.tolist(),
                                  size=[5000.0, 5000.0])])
    small_sequence, patterns = generate_sequence(small_projector.width, small_projector.height)
    view = render_view(scene, small_camera, small_projector, supersample=1)
    frames = render_frames(view, patterns, np.random.default_rng(0))
    _, thermal = small.device(None, "thermal")
    thermal_frames = np.full((1, thermal.height, thermal.width), 900.0, np.float32)
    warm_tables = TriangulationTables()
    outcome = process_scan(frames=frames, sequence=small_sequence, thermal=thermal_frames, rig=small,
                           tables=warm_tables)
    scan_artifacts(frames=frames, sequence=small_sequence, thermal=thermal_frames, outcome=outcome)
    scan_recording("warm-up", field_scene(outcome.field, small, thermal_frames[0]))
    seconds["kernels"] = round(time.perf_counter() - start, 3)
    return seconds
