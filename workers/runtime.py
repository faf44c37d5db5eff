"""What a worker process needs to run jobs: database sessions, artifact store and job tracker.

Built once per process from the settings (spawned worker processes build their own);
the embedded server hands over the runtime it already built with :func:`use_runtime`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from services.db.engine import make_engine, make_sessions, migrate
from services.events.mqtt import EventPublisher
from services.jobs.tracker import JobTracker
from services.settings import Settings, get_settings
from services.storage.artifacts import ArtifactStore


@dataclass
class Runtime:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: ArtifactStore
    tracker: JobTracker


def build_runtime(settings: Settings) -> Runtime:
    """Connect to the database (migrated to head), open the store and the MQTT publisher."""
    engine = make_engine(settings.resolved_database_url, settings.database_schema)
    migrate(engine)
    sessions = make_sessions(engine)
    publisher = (
        EventPublisher(settings.mqtt_host, settings.mqtt_port, settings.topic_prefix) if settings.mqtt_host else None
    )
    return Runtime(settings, engine, sessions, ArtifactStore(settings.resolved_artifact_dir),
                   JobTracker(sessions, publisher))


_lock = threading.Lock()
_runtime: Runtime | None = None


def use_runtime(runtime: Runtime) -> None:
    global _runtime
    with _lock:
        _runtime = runtime


def current_runtime() -> Runtime:
    """This process's runtime, built from the environment's settings on first use."""
    global _runtime
    with _lock:
        if _runtime is None:
            _runtime = build_runtime(get_settings())
        return _runtime
