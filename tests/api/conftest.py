"""Fixtures on the service database of ``tests/conftest.py`` (SQLite and PostgreSQL)."""

import pytest


@pytest.fixture
def runtime(engine, tmp_path):
    """A runtime on the test database with an in-memory broker (jobs are queued, not run)."""
    from services.db.engine import make_sessions
    from services.jobs.tracker import JobTracker
    from services.settings import Settings
    from services.storage.artifacts import ArtifactStore
    from services.runtime import Runtime

    settings = Settings(data_dir=tmp_path, broker_url="", mqtt_host="")
    sessions = make_sessions(engine)
    return Runtime(settings, engine, sessions, ArtifactStore(tmp_path / "artifacts"), JobTracker(sessions))


@pytest.fixture
def job_queue(runtime):
    """The API's job queue on an in-memory broker: messages wait on it, no worker runs them."""
    from services.jobs.queue import JobQueue, job_broker

    return JobQueue(job_broker(runtime.settings), runtime.settings.job_queue)


@pytest.fixture
def client(runtime, job_queue):
    from fastapi.testclient import TestClient

    from api.app import create_app

    with TestClient(create_app(runtime, job_queue), raise_server_exceptions=False) as client:
        yield client


@pytest.fixture
def auth(runtime):
    """Authorization headers of one key per scope."""
    from services.db.apikeys import create_api_key

    with runtime.sessions.begin() as session:
        return {scope: {"Authorization": f"Bearer {create_api_key(session, scope, [scope])[1]}"}
                for scope in ("read", "operate", "admin")}
