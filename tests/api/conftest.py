"""Fixtures on the service database of ``tests/conftest.py`` (SQLite and PostgreSQL)."""

import pytest


@pytest.fixture
def runtime(engine, tmp_path):
    """A runtime on the test database with an in-memory broker (jobs are queued, not run)."""
    from services.db.engine import make_sessions
    from services.jobs.tracker import JobTracker
    from services.settings import Settings
    from services.storage.artifacts import ArtifactStore
    from workers.broker import setup_broker
    from workers.runtime import Runtime

    settings = Settings(data_dir=tmp_path, broker_url="", mqtt_host="")
    sessions = make_sessions(engine)
    setup_broker(settings)
    return Runtime(settings, engine, sessions, ArtifactStore(tmp_path / "artifacts"), JobTracker(sessions))


@pytest.fixture
def client(runtime):
    from fastapi.testclient import TestClient

    from api.app import create_app

    with TestClient(create_app(runtime), raise_server_exceptions=False) as client:
        yield client


@pytest.fixture
def auth(runtime):
    """Authorization headers of one key per scope."""
    from services.db.apikeys import create_api_key

    with runtime.sessions.begin() as session:
        return {scope: {"Authorization": f"Bearer {create_api_key(session, scope, [scope])[1]}"}
                for scope in ("read", "operate", "admin")}
