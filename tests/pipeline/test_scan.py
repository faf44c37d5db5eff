"""The scan use case with a part type: a field the part is not found in keeps the scan and says why."""

import hashlib
import io

import numpy as np

from services.formats.part import load_part
from services.formats.rig import Rig
from services.geometry.camera_model import CameraModel
from services.pipeline.inspect import prepare_part_type
from services.pipeline.scan import StageClock, process_scan, scan_artifacts, scan_capture, scan_result
from services.pipeline.tables import TriangulationTables
from services.simulation.hot_part import write_billet_part
from services.storage.artifacts import ArtifactStore


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


def test_a_stored_scan_keeps_every_file_in_the_store_and_its_result_says_why_it_was_not_inspected(
        small_capture, tmp_path):
    part = prepare_part_type(load_part(write_billet_part(tmp_path / "billet", segments=48)))
    camera = small_capture.rig.devices["camera"]
    thermal = CameraModel(kind="thermal", width=80, height=64, K=[[95, 0, 40], [0, 95, 32], [0, 0, 1]],
                          R=camera.R.tolist(), t=camera.t.tolist())
    rig = Rig({**small_capture.rig.devices, "thermal": thermal})
    room = np.full((1, 64, 80), 25.0, np.float32)
    store, published, stages = ArtifactStore(tmp_path / "store"), [], []
    clock = StageClock(lambda stage, fraction: stages.append((stage, fraction)))
    stored = scan_capture(scan_id="s1", frames=small_capture.frames, sequence=small_capture.sequence,
                          thermal=room, rig=rig, tables=TriangulationTables(), store=store, captured_at=12.5,
                          part=part, clock=clock, publish=lambda scene, at: published.append(at))
    assert set(stored.artifacts) == {"frames.npy", "thermal.npy", "sequence.json", "exposure.json", "cloud.ply",
                                     "field.ply", "field.rrd"}
    for digest in stored.artifacts.values():
        assert hashlib.sha256(store.read_bytes(digest)).hexdigest() == digest
    assert np.array_equal(np.load(io.BytesIO(store.read_bytes(stored.artifacts["frames.npy"]))), small_capture.frames)
    assert published == [12.5]
    assert [stage for stage, _ in stages] == ["reconstruct", "fuse", "inspect", "stream", "store"]
    result = scan_result(scan_id="s1", stored=stored, part_type_id="pt1", stage_seconds=clock.seconds)
    assert result["verdict"] == "NotDecidable" and result["features"] == [] and result["part_type_id"] == "pt1"
    assert result["inspection_error"] == stored.outcome.inspection_error
    assert result["summary"]["point_count"] == len(stored.outcome.field) and set(clock.seconds) >= {"fuse", "store"}
