"""Engines and sessions: SQLite in WAL mode (embedded default) or PostgreSQL (production)."""

from __future__ import annotations

import re
import zlib
from importlib import resources
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import Engine, create_engine, event, text
from sqlalchemy.orm import Session, sessionmaker

# Shipped inside the package (package data), so that an installed wheel migrates as a checkout does; an installed
# package is a directory on disk, which is what Alembic reads its scripts from.
MIGRATIONS_DIR = Path(str(resources.files("services.db") / "migrations"))
# The key of the PostgreSQL advisory lock that lets one process at a time migrate (several start at once).
_MIGRATION_LOCK = zlib.crc32(b"thermofield-migrations")
_SCHEMA_NAME = re.compile(r"^[a-z_][a-z0-9_]{0,62}$")


def make_engine(url: str, schema: str | None = None) -> Engine:
    """An engine for ``url``; SQLite gets WAL, foreign keys and a busy timeout, PostgreSQL a search path.

    Parameters
    ----------
    url : str
        SQLAlchemy URL, ``sqlite:///path`` or ``postgresql+psycopg://...``.
    schema : str, optional
        PostgreSQL schema that holds the tables (created if missing), isolating
        several deployments or test sessions in one database.
    """
    if url.startswith("sqlite"):
        database = url.split("///", 1)[-1]
        if database and database != ":memory:":
            Path(database).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})
        event.listen(engine, "connect", _configure_sqlite)
        return engine
    if url.startswith("postgresql://"):
        url = "postgresql+psycopg://" + url.removeprefix("postgresql://")
    engine = create_engine(url, pool_pre_ping=True, pool_size=10, max_overflow=20)
    if schema is not None:
        if not _SCHEMA_NAME.match(schema):
            raise ValueError(f"The database schema name {schema!r} must be lower-case letters, digits and '_'.")
        with engine.begin() as connection:
            connection.execute(text(f"CREATE SCHEMA IF NOT EXISTS {schema}"))
        engine.dispose()  # the pooled connection predates the search path
        event.listen(engine, "connect", lambda connection, _: _set_search_path(connection, schema))
    return engine


def _configure_sqlite(connection, _record) -> None:
    cursor = connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.close()


def _set_search_path(connection, schema: str) -> None:
    cursor = connection.cursor()
    cursor.execute(f"SET search_path TO {schema}")
    cursor.close()
    connection.commit()


def make_sessions(engine: Engine) -> sessionmaker[Session]:
    return sessionmaker(engine, expire_on_commit=False)


def migrate(engine: Engine) -> None:
    """Bring the database to the newest Alembic revision (``services/db/migrations/``).

    On PostgreSQL the migration holds a transaction-level advisory lock: when the API and
    the workers start at once, one process migrates and the others wait, then find the
    database at head and do nothing.
    """
    run_alembic(engine, "upgrade", "head")


def schema_revision(engine: Engine) -> str:
    """The database's Alembic revision (raises the driver's error when it does not answer or is not migrated)."""
    with engine.connect() as connection:
        return connection.execute(text("SELECT version_num FROM alembic_version")).scalar_one()


def run_alembic(engine: Engine, action: str, revision: str) -> None:
    """``alembic upgrade|downgrade <revision>`` on ``engine`` in one transaction.

    On SQLite, foreign keys are off while the migration runs: Alembic's batch mode
    rebuilds a table by copying it and dropping the original, which a referencing
    table would otherwise forbid; ``PRAGMA foreign_key_check`` verifies the result.
    """
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    sqlite = engine.dialect.name == "sqlite"
    with engine.connect() as connection:
        if sqlite:
            connection.exec_driver_sql("PRAGMA foreign_keys=OFF")  # takes effect only outside a transaction
            connection.commit()
        try:
            with connection.begin():
                if engine.dialect.name == "postgresql":
                    connection.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": _MIGRATION_LOCK})
                config.attributes["connection"] = connection
                getattr(command, action)(config, revision)
                if sqlite and connection.exec_driver_sql("PRAGMA foreign_key_check").first() is not None:
                    raise RuntimeError(f"alembic {action} {revision} left rows whose foreign keys point nowhere")
        finally:
            if sqlite:
                connection.exec_driver_sql("PRAGMA foreign_keys=ON")
                connection.commit()
