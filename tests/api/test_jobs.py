"""The status poll's path (``GET /v1/jobs/{id}``): the job read on the DBAPI connection gives what the ORM gives,
on SQLite and PostgreSQL."""

from datetime import UTC, datetime, timedelta

from services.db.jobs import JobRow, load_job
from services.db.models import Job
from services.jobs.tracker import job_state

PROBLEM = "application/problem+json"


def _succeeded_scan_job(runtime) -> str:
    started = datetime(2026, 12, 2, 8, 27, 0, 123456, tzinfo=UTC)
    with runtime.sessions.begin() as session:
        job = Job(kind="scan", status="succeeded", stage="done", fraction=1.0, attempts=2, worker="host:41",
                  error=None, params={"scan_id": "s1", "calibration_set_id": "c1"},
                  result={"artifacts": {"field.ply": "ab" * 32, "cloud.ply": "cd" * 32},
                          "summary": {"point_count": 12, "temperature": {"mean": 951.25}, "glow": None}},
                  started_at=started, finished_at=started + timedelta(seconds=4.5))
        session.add(job)
        session.flush()
        return job.id


def test_the_read_gives_the_orm_values(runtime):
    job_id = _succeeded_scan_job(runtime)
    for _ in range(7):  # past psycopg's threshold for a server-side prepared statement (5 runs)
        row = load_job(runtime.engine, job_id)
    with runtime.sessions() as session:
        job = session.get(Job, job_id)
        assert row == JobRow(*(getattr(job, name) for name in JobRow._fields))
        assert job_state(row) == job_state(job)
    assert row.created_at.utcoffset() == timedelta(0) and row.finished_at.utcoffset() == timedelta(0)
    assert load_job(runtime.engine, "no such job") is None


def test_a_poll_answers_the_job_state_with_links(client, auth, runtime):
    job_id = _succeeded_scan_job(runtime)
    response = client.get(f"/v1/jobs/{job_id}", headers=auth["read"])
    assert response.status_code == 200 and response.headers["content-type"] == "application/json"
    body = response.json()
    with runtime.sessions() as session:
        state = job_state(session.get(Job, job_id))
    assert {name: body[name] for name in ("job_id", "status", "stage", "attempts", "worker", "result", "scan_id")} == \
        {name: state[name] for name in ("job_id", "status", "stage", "attempts", "worker", "result", "scan_id")}
    assert body["finished_at"] == "2026-12-02T08:27:04.623456Z"
    assert body["links"] == {"self": f"/v1/jobs/{job_id}", "events": f"/v1/jobs/{job_id}/events",
                             "field.ply": f"/v1/jobs/{job_id}/artifacts/field.ply",
                             "cloud.ply": f"/v1/jobs/{job_id}/artifacts/cloud.ply"}
    missing = client.get("/v1/jobs/nope", headers=auth["read"])
    assert missing.status_code == 404 and missing.headers["content-type"] == PROBLEM


def test_a_key_revoked_by_another_process_stops_working_within_the_cache_time(client, auth, runtime):
    """Another API process (or ``thermofield apikey revoke``) revokes in the database alone: this process's cached
    key works on until its cache time is over, never longer."""
    import time

    from api.deps import KeyCache
    from api.ratelimit import RateLimiter
    from services.db.apikeys import create_api_key, revoke_api_key

    client.app.state.key_cache = KeyCache(seconds=0.5)
    client.app.state.auth_failures = RateLimiter(0, 1)  # the loop below sends the revoked key ever again
    job_id = _succeeded_scan_job(runtime)
    with runtime.sessions.begin() as session:
        key, secret = create_api_key(session, "mes", ["read"])
    mes = {"Authorization": f"Bearer {secret}"}
    assert client.get(f"/v1/jobs/{job_id}", headers=mes).status_code == 200  # now cached
    with runtime.sessions.begin() as session:
        revoke_api_key(session, key.id)
    revoked_at = time.monotonic()
    statuses = []
    while time.monotonic() - revoked_at < 1.5:
        statuses.append((time.monotonic() - revoked_at, client.get(f"/v1/jobs/{job_id}", headers=mes).status_code))
    assert all(status == 401 for elapsed, status in statuses if elapsed > 0.5), statuses
    assert statuses[-1][1] == 401
    assert client.get(f"/v1/jobs/{job_id}", headers=auth["read"]).status_code == 200  # other keys unaffected


def test_the_jobs_listing_is_the_same_state(client, auth, runtime):
    job_id = _succeeded_scan_job(runtime)
    listed = client.get("/v1/jobs", headers=auth["read"]).json()
    polled = client.get(f"/v1/jobs/{job_id}", headers=auth["read"]).json()
    assert [job for job in listed if job["job_id"] == job_id] == [polled]
