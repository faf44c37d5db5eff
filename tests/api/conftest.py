"""Service databases for tests: SQLite in a temporary directory and the machine's PostgreSQL
(database ``test``, a fresh schema per test, dropped afterwards)."""

import uuid

import pytest
from sqlalchemy import text

from services.db.engine import make_engine, migrate

POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


@pytest.fixture(params=["sqlite", "postgresql"])
def engine(request, tmp_path):
    if request.param == "sqlite":
        engine = make_engine(f"sqlite:///{tmp_path / 'service.db'}")
        migrate(engine)
        yield engine
        engine.dispose()
        return
    schema = f"tf_test_{uuid.uuid4().hex[:12]}"
    engine = make_engine(POSTGRES_URL, schema)
    migrate(engine)
    yield engine
    engine.dispose()
    with make_engine(POSTGRES_URL).begin() as connection:
        connection.execute(text(f"DROP SCHEMA {schema} CASCADE"))


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
