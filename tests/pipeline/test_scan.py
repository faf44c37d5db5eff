"""The scan use case with a part type: a field the part is not found in keeps the scan and says why."""

import numpy as np

from services.formats.part import load_part
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.pipeline.inspect import prepare_part_type
from services.pipeline.scan import process_scan, scan_artifacts
from services.pipeline.tables import TriangulationTables
from services.simulation.hot_part import write_billet_part


def test_a_cold_field_is_not_inspected_but_the_scan_keeps_its_files(small_capture, tmp_path):
    part = prepare_part_type(load_part(write_billet_part(tmp_path / "billet", segments=48)))
    camera = small_capture.rig.devices["camera"]
    thermal = CameraModel(kind="thermal", width=80, height=64, K=[[95, 0, 40], [0, 95, 32], [0, 0, 1]],
                          R=camera.R.tolist(), t=camera.t.tolist())
    rig = Rig({**small_capture.rig.devices, "thermal": thermal})
    room = np.full((1, 64, 80), 25.0, np.float32)  # nothing is hot: no part to inspect
    outcome = process_scan(frames=small_capture.frames, sequence=small_capture.sequence, thermal=room, rig=rig,
                           tables=TriangulationTables(), part=part)
    assert outcome.inspection is None and len(outcome.field) > 1000
    assert outcome.inspection_error.startswith("the scan's field (part type 'billet-90'): ")
    assert "degC hot" in outcome.inspection_error
    files = scan_artifacts(frames=small_capture.frames, sequence=small_capture.sequence, thermal=room,
                           outcome=outcome)
    assert {"cloud.ply", "field.ply", "frames.npy"} <= set(files) and "report.json" not in files
