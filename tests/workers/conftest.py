"""Fixtures on the service database of ``tests/conftest.py`` (SQLite and PostgreSQL)."""

import pytest

from services.db.engine import make_sessions
from services.jobs.tracker import JobTracker
from services.settings import Settings
from services.storage.artifacts import ArtifactStore
from workers.broker import setup_broker
from services.runtime import Runtime, use_runtime


@pytest.fixture
def broker(engine, tmp_path):
    """The embedded broker with the service middleware, its runtime on the test database."""
    settings = Settings(data_dir=tmp_path, broker_url="", mqtt_host="", compute_threads=1, warm_up=False)
    sessions = make_sessions(engine)
    use_runtime(Runtime(settings, engine, sessions, ArtifactStore(tmp_path / "artifacts"), JobTracker(sessions)))
    return setup_broker(settings)
