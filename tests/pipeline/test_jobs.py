"""The jobs on a stored scan, as the workers run them: each reads its rows through services/db and its files
from the store, on SQLite and PostgreSQL."""

import numpy as np
import pytest

from services.db.calibrations import add_calibration_set
from services.db.engine import make_sessions
from services.db.models import Scan, new_id
from services.formats.ply import cloud_from_ply
from services.formats.rig import Rig, rig_to_json
from services.geometry.camera_model import CameraModel
from services.jobs.tracker import JobTracker
from services.pipeline.field import fuse_field
from services.pipeline.jobs import fuse_job, reconstruct_job, station_rig
from services.pipeline.reconstruct import reconstruct_capture
from services.pipeline.scan import capture_artifacts
from services.pipeline.tables import TriangulationTables
from services.runtime import Runtime
from services.settings import Settings
from services.storage.artifacts import ArtifactStore


class _Progress(JobTracker):
    """The tracker, keeping each stage the jobs report."""

    def __init__(self, sessions) -> None:
        super().__init__(sessions)
        self.stages: list[tuple[str, str, float]] = []

    def progress(self, job_id: str, stage: str, fraction: float) -> None:
        self.stages.append((job_id, stage, fraction))
        super().progress(job_id, stage, fraction)


@pytest.fixture
def stored_scan(engine, tmp_path, small_capture):
    """A runtime on the test database and a scan whose capture (with a 25 degC thermal frame) is stored."""
    camera = small_capture.rig.devices["camera"]
    thermal = CameraModel(kind="thermal", width=80, height=64, K=[[95, 0, 40], [0, 95, 32], [0, 0, 1]],
                          R=camera.R.tolist(), t=camera.t.tolist())
    rig = Rig({**small_capture.rig.devices, "thermal": thermal})
    sessions = make_sessions(engine)
    runtime = Runtime(Settings(data_dir=tmp_path, broker_url="", mqtt_host="", warm_up=False), engine, sessions,
                      ArtifactStore(tmp_path / "artifacts"), _Progress(sessions))
    runtime.tables = TriangulationTables()  # in memory only
    files = capture_artifacts(frames=small_capture.frames, sequence=small_capture.sequence,
                              thermal=np.full((1, 64, 80), 25.0, np.float32))
    with sessions.begin() as session:
        calibration = add_calibration_set(session, name="true rig", station=runtime.settings.station,
                                          rig_sha256=runtime.store.put_bytes(rig_to_json(rig).encode()),
                                          source="upload")
        scan_job = runtime.tracker.create(session, "scan", {})
        scan = Scan(id=new_id(), station=runtime.settings.station, calibration_set_id=calibration.id,
                    job_id=scan_job.id, artifacts={name: runtime.store.put_bytes(data) for name, data in files.items()})
        session.add(scan)
        params = {"scan_id": scan.id, "calibration_set_id": calibration.id}
    return runtime, rig, params


def _job(runtime, kind, params) -> str:
    with runtime.sessions.begin() as session:
        return runtime.tracker.create(session, kind, params).id


def test_reconstruct_then_fuse_a_stored_scan(stored_scan, small_capture):
    runtime, rig, params = stored_scan
    reconstruct_id = _job(runtime, "reconstruct", params)
    reconstructed = reconstruct_job(runtime=runtime, job_id=reconstruct_id)
    cloud = cloud_from_ply(runtime.store.read_bytes(reconstructed["artifacts"]["cloud.ply"]))
    expected = reconstruct_capture(frames=small_capture.frames, sequence=small_capture.sequence, rig=rig,
                                   tables=TriangulationTables()).cloud
    assert reconstructed["point_count"] == len(cloud) == len(expected) > 1000
    assert np.array_equal(cloud["z"], expected["z"])

    fuse_id = _job(runtime, "fuse", {**params, "cloud_sha256": reconstructed["artifacts"]["cloud.ply"]})
    fused = fuse_job(runtime=runtime, job_id=fuse_id)
    field = cloud_from_ply(runtime.store.read_bytes(fused["artifacts"]["field.ply"]))
    assert len(field) == len(cloud) and fused["summary"]["point_count"] == len(field)
    expected = fuse_field(cloud=cloud, rig=rig, thermal=[(None, np.full((1, 64, 80), 25.0, np.float32))])
    assert np.array_equal(field["temperature"], expected["temperature"], equal_nan=True)
    seen = np.isfinite(field["temperature"])
    assert seen.sum() > 1000 and np.allclose(field["temperature"][seen], 25.0)  # the thermal camera sees part
    assert fused["summary"]["points_with_temperature"] == seen.sum()
    assert fused["summary"]["temperature"]["max"] == pytest.approx(25.0)
    assert runtime.tracker.stages == [(reconstruct_id, "reconstruct", 0.1), (fuse_id, "fuse", 0.1)]


def test_a_job_on_a_scan_that_is_not_there_says_so(stored_scan):
    runtime, _, params = stored_scan
    with pytest.raises(LookupError, match="there is no scan 'gone'"):
        reconstruct_job(runtime=runtime, job_id=_job(runtime, "reconstruct", {**params, "scan_id": "gone"}))
    with pytest.raises(LookupError, match="there is no job 'unknown'"):
        fuse_job(runtime=runtime, job_id="unknown")


def test_the_station_rig_is_its_active_calibration_sets(stored_scan):
    runtime, rig, params = stored_scan
    assert station_rig(runtime=runtime) is None  # its only set is not active
    with runtime.sessions.begin() as session:
        add_calibration_set(session, name="active", station=runtime.settings.station,
                            rig_sha256=runtime.store.put_bytes(rig_to_json(rig).encode()), source="upload",
                            activate=True)
    assert set(station_rig(runtime=runtime).devices) == {"camera", "projector", "thermal"}
