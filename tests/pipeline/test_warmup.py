"""The service's warm-up: the active calibration's table built, every stage of a scan run once."""

import numpy as np

from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.tables import TriangulationTables
from services.pipeline.warmup import _plane_frames, warm_up
from services.simulation.presets import forging_rig
from services.structured_light.patterns import generate_sequence


def test_warm_up_builds_the_calibrations_table_once_and_times_its_parts():
    rig = forging_rig()
    sequence = generate_sequence(*rig.device(None, "projector")[1].size)[0]
    tables = TriangulationTables()
    seconds = warm_up(rig=rig, sequence=sequence, tables=tables)
    assert set(seconds) == {"table", "stages"} and all(value > 0 for value in seconds.values())
    assert tables.built == 1  # the scan of the plane used the calibration's own table, at the rig's full size
    warm_up(rig=rig, sequence=sequence, tables=tables)
    assert tables.built == 1  # the second warm-up (another worker process's) finds it


def test_the_synthetic_plane_capture_decodes_to_a_plane_at_the_rigs_meeting_point():
    rig = forging_rig()
    _, camera = rig.device(None, "camera")
    _, projector = rig.device(None, "projector")
    sequence, patterns = generate_sequence(projector.width, projector.height)
    frames = _plane_frames(camera, projector, patterns, np.random.default_rng(0))
    assert frames.shape == (len(sequence.frames), camera.height, camera.width) and frames.dtype == np.uint8
    cloud = reconstruct_capture(frames=frames, sequence=sequence, rig=rig, tables=TriangulationTables()).cloud
    assert len(cloud) > 0.3 * camera.width * camera.height
    depth = (cloud.points - camera.centre) @ camera.R[2]  # along the camera's axis: the plane is square to it
    assert np.ptp(depth) < 0.02 * np.median(depth)
