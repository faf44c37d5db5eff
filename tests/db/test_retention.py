"""Retention on the real databases and a real store: which scans keep what, idempotency expiry, the sweep; the
periodic task (MaintenanceThread with the settings' policy and interval) and `thermofield maintenance` as a process."""

import os
import subprocess
import sys
import time
from datetime import UTC, datetime, timedelta

from sqlalchemy import text

from services.db.engine import make_sessions
from services.db.models import ApiKey, CalibrationSet, IdempotencyRecord, Job, PartType, Scan
from services.settings import Settings
from services.storage.artifacts import ArtifactStore
from services.storage.retention import MaintenanceThread, RetentionPolicy, run_maintenance

NOW = datetime(2026, 6, 1, 12, 0, tzinfo=UTC)
FIELDS = ("cloud.ply", "field.ply", "field.rrd")
RAW = ("frames.npy", "thermal.npy", "sequence.json")


def _scan(session, store, calibration, station, days_old, name, now=NOW):
    created = now - timedelta(days=days_old)
    artifacts = {artifact: store.put_bytes(f"{name} {artifact}".encode() * 100) for artifact in FIELDS + RAW}
    job = Job(kind="scan", status="succeeded", params={"scan_id": name}, created_at=created,
              result={"scan_id": name, "artifacts": dict(artifacts)})
    session.add(job)
    session.flush()
    session.add(Scan(id=name, station=station, job_id=job.id, calibration_set_id=calibration.id,
                     artifacts=artifacts, summary={"point_count": 1}, created_at=created))
    return artifacts


def test_retention_keeps_the_newest_scans_or_days_and_raw_frames_shorter(engine, tmp_path):
    sessions = make_sessions(engine)
    store = ArtifactStore(tmp_path / "artifacts")
    with sessions.begin() as session:
        calibration = CalibrationSet(name="rig", station="s1", source="upload", rig_sha256=store.put_bytes(b"rig"))
        session.add(calibration)
        session.flush()
        blobs = {name: _scan(session, store, calibration, station, days, name) for name, station, days in [
            ("new", "s1", 0.5), ("two-days", "s1", 2.0), ("young-but-third", "s1", 2.5), ("old", "s1", 10.0),
            ("other-station-old", "s2", 10.0)]}
        rerun = Job(kind="reconstruct", status="succeeded", params={"scan_id": "old"},
                    result={"artifacts": {"cloud.ply": store.put_bytes(b"rerun cloud")}})
        session.add(rerun)
        part_files = (store.put_bytes(b"part file"), store.put_bytes(b"nominal mesh"))
        session.add(PartType(name="billet", station="s1", material="carbon-steel", part_sha256=part_files[0],
                             mesh_sha256=part_files[1]))
        key = ApiKey(name="k", secret_sha256="0" * 64, scopes="operate")
        session.add(key)
        session.flush()
        for age_days, idempotency_key in ((2.0, "stale"), (0.1, "fresh")):
            session.add(IdempotencyRecord(api_key_id=key.id, key=idempotency_key, request_sha256="x", status_code=202,
                                          body="{}", created_at=NOW - timedelta(days=age_days)))
    in_flight = store.put_bytes(b"written by a running job, not yet in a row")
    old_blob = store.path(blobs["old"]["frames.npy"])
    os.utime(store.path(in_flight), (time.time(), time.time()))
    for digest, path in store.blobs():  # everything else was written "long ago"
        if digest != in_flight:
            os.utime(path, (time.time() - 7200, time.time() - 7200))
    before = sum(path.stat().st_size for _, path in store.blobs())

    policy = RetentionPolicy(keep_scans=2, keep_days=3.0, raw_frames_days=1.0, idempotency_ttl_s=86400.0)
    report = run_maintenance(sessions, store, policy, now=NOW)

    with sessions() as session:
        kept = {scan.id: set(scan.artifacts) for scan in session.query(Scan)}
        assert kept["new"] == set(FIELDS + RAW)  # newest, and younger than the raw-frame limit
        assert kept["two-days"] == set(FIELDS)  # among the newest two: fields kept, raw frames older than 1 day
        assert kept["young-but-third"] == set(FIELDS)  # third, but younger than 3 days
        assert kept["old"] == set()  # neither among the newest two nor younger than 3 days
        assert kept["other-station-old"] == set(FIELDS)  # the newest of its own station
        old_jobs = [job for job in session.query(Job) if job.params.get("scan_id") == "old"]
        assert len(old_jobs) == 2 and all(job.result["artifacts"] == {} for job in old_jobs)
        assert session.get(Scan, "old").summary == {"point_count": 1}  # the row and its summary stay
        assert [record.key for record in session.query(IdempotencyRecord)] == ["fresh"]
    assert (report.scans_expired, report.raw_frames_expired, report.idempotency_records_deleted) == (1, 3, 1)
    assert not old_blob.exists() and store.exists(in_flight)  # swept; the fresh blob is within the grace period
    remaining = {digest for digest, _ in store.blobs()}
    assert all(blobs["new"][name] in remaining for name in FIELDS + RAW)
    assert not any(blobs["two-days"][name] in remaining for name in RAW)
    with sessions() as session:
        assert store.exists(session.scalar(session.query(CalibrationSet.rig_sha256).statement))
    assert all(store.exists(digest) for digest in part_files)  # a part type keeps its files, however old
    after = sum(path.stat().st_size for _, path in store.blobs())
    assert report.bytes_freed == before - after > 0
    assert run_maintenance(sessions, store, policy, now=NOW).blobs_deleted == 0  # idempotent


def _two_scans_written_long_ago(sessions, store):
    """A new and a 10-day-old scan of one station, every blob written two hours ago (past the sweep's grace)."""
    now = datetime.now(UTC)
    with sessions.begin() as session:
        calibration = CalibrationSet(name="rig", station="s1", source="upload", rig_sha256=store.put_bytes(b"rig"))
        session.add(calibration)
        session.flush()
        blobs = {name: _scan(session, store, calibration, "s1", days, name, now) for name, days in
                 (("new", 0.01), ("old", 10.0))}
    for _, path in store.blobs():
        os.utime(path, (time.time() - 7200, time.time() - 7200))
    return blobs


def _kept(sessions) -> dict[str, set[str]]:
    with sessions() as session:
        return {scan.id: set(scan.artifacts) for scan in session.query(Scan)}


SWEEPING = {"retention_keep_scans": 1, "retention_keep_days": 3.0, "retention_raw_frames_days": 1.0}


def test_the_maintenance_thread_sweeps_every_interval_of_the_settings(engine, tmp_path):
    sessions, store = make_sessions(engine), ArtifactStore(tmp_path / "artifacts")
    blobs = _two_scans_written_long_ago(sessions, store)
    never = Settings(data_dir=tmp_path, maintenance_interval_s=0, **SWEEPING)
    with MaintenanceThread(sessions, store, never.retention_policy, never.maintenance_interval_s):
        time.sleep(0.5)  # the test's window: with interval 0 no sweep comes in it
    assert _kept(sessions)["old"] == set(FIELDS + RAW)  # interval 0: never runs

    settings = Settings(data_dir=tmp_path, maintenance_interval_s=0.3, **SWEEPING)
    assert settings.retention_policy.keep_scans == 1
    started = time.monotonic()
    with MaintenanceThread(sessions, store, settings.retention_policy, settings.maintenance_interval_s):
        while _kept(sessions)["old"] and time.monotonic() - started < 30:
            time.sleep(0.05)
        swept_after = time.monotonic() - started
        while store.exists(blobs["old"]["frames.npy"]) and time.monotonic() - started < 30:
            time.sleep(0.05)
        # new blobs past the grace period, written while the thread runs, are swept by a later run
        late = store.put_bytes(b"an orphan written after the first run")
        os.utime(store.path(late), (time.time() - 7200, time.time() - 7200))
        while store.exists(late) and time.monotonic() - started < 30:
            time.sleep(0.05)
    assert _kept(sessions) == {"new": set(FIELDS + RAW), "old": set()}
    assert 0.3 <= swept_after < 30  # the first run comes after one interval, not at once
    assert not any(store.exists(blobs["old"][name]) for name in FIELDS + RAW)
    assert not store.exists(late)  # a second run swept it: the thread keeps running
    assert all(store.exists(blobs["new"][name]) for name in FIELDS + RAW)


def test_thermofield_maintenance_applies_the_environments_policy_once(engine, tmp_path):
    sessions, store = make_sessions(engine), ArtifactStore(tmp_path / "artifacts")
    blobs = _two_scans_written_long_ago(sessions, store)
    environment = {**os.environ, "THERMOFIELD_DATABASE_URL": engine.url.render_as_string(hide_password=False),
                   "THERMOFIELD_ARTIFACT_DIR": str(store.root), "THERMOFIELD_RETENTION_KEEP_SCANS": "1",
                   "THERMOFIELD_RETENTION_KEEP_DAYS": "3", "THERMOFIELD_RETENTION_RAW_FRAMES_DAYS": "1"}
    if engine.dialect.name == "postgresql":
        with engine.connect() as connection:
            environment["THERMOFIELD_DATABASE_SCHEMA"] = connection.execute(text("SHOW search_path")).scalar()
    done = subprocess.run([sys.executable, "-m", "services.cli.main", "maintenance"], env=environment,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("thermofield: 1 scans expired") and "6 blobs" in done.stdout, done.stdout
    assert _kept(sessions) == {"new": set(FIELDS + RAW), "old": set()}
    assert not any(store.exists(blobs["old"][name]) for name in FIELDS + RAW)
    assert all(store.exists(blobs["new"][name]) for name in FIELDS + RAW)


def test_the_blob_grace_period_is_the_settings(engine, tmp_path):
    """An unreferenced blob younger than THERMOFIELD_RETENTION_BLOB_GRACE_S is kept, an older one swept."""
    sessions, store = make_sessions(engine), ArtifactStore(tmp_path / "artifacts")
    policy = Settings(data_dir=tmp_path, retention_blob_grace_s=100).retention_policy
    assert policy.blob_grace_s == 100
    young, old = store.put_bytes(b"an orphan 50 s old"), store.put_bytes(b"an orphan 150 s old")
    for digest, age in ((young, 50), (old, 150)):
        os.utime(store.path(digest), (time.time() - age, time.time() - age))
    run_maintenance(sessions, store, policy)
    assert store.exists(young) and not store.exists(old)


def test_a_station_scans_raw_files_per_head_and_thermal_camera_expire_with_its_head_jobs_parameters(engine, tmp_path):
    """A station scan keeps its capture per head (heads/<head>/frames.npy, sequence.json) and per thermal camera
    (thermal/<device>.npy), and each head's job names its head's frames in its parameters: all of it is raw."""
    sessions, store = make_sessions(engine), ArtifactStore(tmp_path / "artifacts")
    heads = ("north", "south")
    raw = [f"heads/{head}/{name}" for head in heads for name in ("frames.npy", "sequence.json")] + ["thermal/ir.npy"]
    kept = [f"heads/{head}/{name}" for head in heads for name in ("exposure.json", "cloud.ply")] + list(FIELDS)
    with sessions.begin() as session:
        calibration = CalibrationSet(name="rig", station="s1", source="upload", rig_sha256=store.put_bytes(b"rig"))
        session.add(calibration)
        session.flush()
        created = NOW - timedelta(days=2)
        artifacts = {name: store.put_bytes(name.encode() * 100) for name in raw + kept}
        parent = Job(kind="scan", status="succeeded", params={"scan_id": "station"}, created_at=created,
                     result={"scan_id": "station", "artifacts": dict(artifacts)})
        head_jobs = [Job(kind="scan_head", status="succeeded", created_at=created, params={
            "scan_id": "station", "head": head, **{name: artifacts[f"heads/{head}/{name}"]
                                                   for name in ("frames.npy", "sequence.json", "exposure.json")}},
            result={"head": head, "artifacts": {f"heads/{head}/cloud.ply": artifacts[f"heads/{head}/cloud.ply"]}})
            for head in heads]
        session.add_all([parent, *head_jobs])
        session.flush()
        session.add(Scan(id="station", station="s1", job_id=parent.id, calibration_set_id=calibration.id,
                         artifacts=artifacts, summary={"point_count": 1}, created_at=created))
    for _, path in store.blobs():
        os.utime(path, (time.time() - 7200, time.time() - 7200))

    report = run_maintenance(sessions, store, RetentionPolicy(keep_scans=5, keep_days=3.0, raw_frames_days=1.0),
                             now=NOW)

    assert report.raw_frames_expired == 1 and report.scans_expired == 0
    assert _kept(sessions)["station"] == set(kept)
    with sessions() as session:
        for job in session.query(Job).filter(Job.kind == "scan_head"):
            assert set(job.params) == {"scan_id", "head", "exposure.json"}  # the frames' digests are gone
            assert len(job.result["artifacts"]) == 1  # the head's cloud stays
    assert not any(store.exists(artifacts[name]) for name in raw)
    assert all(store.exists(artifacts[name]) for name in kept)
