"""What a worker process needs to run jobs: database sessions, artifact store, job tracker, and (built
on first use) the triangulation tables, parsed rigs and the live Rerun view.

Built once per process from the settings (spawned worker processes build their own);
the embedded server hands over the runtime it already built with :func:`use_runtime`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from services.db.engine import make_engine, make_sessions, migrate
from services.events.mqtt import EventPublisher
from services.jobs.tracker import JobTracker
from services.settings import Settings, get_settings
from services.storage.artifacts import ArtifactStore

if TYPE_CHECKING:  # the science is imported by the worker's first job, never by the API process
    from services.formats.rig import Rig
    from services.inspection.inspect import PreparedPart
    from services.pipeline.tables import TriangulationTables
    from services.streaming.recording import StationView


@dataclass
class Runtime:
    settings: Settings
    engine: Engine
    sessions: sessionmaker[Session]
    store: ArtifactStore
    tracker: JobTracker
    ready: threading.Event = field(default_factory=lambda: _set(threading.Event()), repr=False)
    """Cleared while the process warms up (see ``workers.actors.warm_up_runtime``); /readyz waits for it."""
    _rigs: dict[str, Rig] = field(default_factory=dict, repr=False)
    _parts: dict[tuple[str, str], PreparedPart] = field(default_factory=dict, repr=False)
    _station_view: StationView | None = field(default=None, repr=False)

    @cached_property
    def tables(self) -> TriangulationTables:
        """The triangulation tables of this process, kept beside the artifacts (shared by the workers)."""
        from services.pipeline.tables import TriangulationTables

        return TriangulationTables(self.settings.resolved_artifact_dir / "tables")

    def rig(self, digest: str, source: str) -> Rig:
        """The rig stored under ``digest``, parsed once per process."""
        from services.formats.rig import parse_rig

        if digest not in self._rigs:
            self._rigs[digest] = parse_rig(self.store.read_bytes(digest).decode(), source)
        return self._rigs[digest]

    def part_type(self, part_sha256: str, mesh_sha256: str, source: str) -> PreparedPart:
        """The part type stored as this part file and mesh, loaded and prepared once per process."""
        from services.formats.part import parse_part_with_mesh
        from services.pipeline.inspect import prepare_part_type

        key = (part_sha256, mesh_sha256)
        if key not in self._parts:
            part = parse_part_with_mesh(self.store.read_bytes(part_sha256).decode(), self.store.read_bytes(mesh_sha256),
                                        source, f"{source}: mesh")
            self._parts[key] = prepare_part_type(part)
        return self._parts[key]

    def station_view(self) -> StationView:
        """The station's live Rerun view (connects on its first publish)."""
        from services.streaming.proxy import proxy_url
        from services.streaming.recording import StationView

        with _lock:
            if self._station_view is None:
                settings = self.settings
                self._station_view = StationView(proxy_url(settings.rerun_host, settings.rerun_port), settings.station)
            return self._station_view

    def close_station_view(self) -> None:
        """Send what the live view buffered and disconnect it (before the Rerun proxy stops)."""
        with _lock:
            if self._station_view is not None:
                self._station_view.close()
                self._station_view = None


def _set(event: threading.Event) -> threading.Event:
    event.set()
    return event


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
