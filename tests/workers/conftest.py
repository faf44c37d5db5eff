"""Service databases for tests: SQLite in a temporary directory and the machine's PostgreSQL
(database ``test``, a fresh schema per test, dropped afterwards)."""

import uuid

import pytest
from sqlalchemy import text

from services.db.engine import make_engine, make_sessions, migrate
from services.jobs.tracker import JobTracker
from services.settings import Settings
from services.storage.artifacts import ArtifactStore
from workers.broker import setup_broker
from workers.runtime import Runtime, use_runtime

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
def broker(engine, tmp_path):
    """The embedded broker with the service middleware, its runtime on the test database."""
    settings = Settings(data_dir=tmp_path, broker_url="", mqtt_host="", compute_threads=1)
    sessions = make_sessions(engine)
    use_runtime(Runtime(settings, engine, sessions, ArtifactStore(tmp_path / "artifacts"), JobTracker(sessions)))
    return setup_broker(settings)
