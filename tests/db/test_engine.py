from sqlalchemy import inspect, text

from services.db.engine import make_engine, make_sessions, migrate
from services.db.models import Job


def test_migration_creates_every_table(engine):
    tables = set(inspect(engine).get_table_names())
    assert {"api_keys", "jobs", "scans", "calibration_sets", "idempotency_records", "alembic_version"} <= tables


def test_migrating_twice_is_harmless_and_keeps_rows(engine):
    sessions = make_sessions(engine)
    with sessions.begin() as session:
        session.add(Job(id="j1", kind="scan", params={"a": 1}))
    migrate(engine)
    with sessions() as session:
        assert session.get(Job, "j1").params == {"a": 1}


def test_sqlite_runs_in_wal_mode(tmp_path):
    engine = make_engine(f"sqlite:///{tmp_path / 'x.db'}")
    with engine.connect() as connection:
        assert connection.execute(text("PRAGMA journal_mode")).scalar_one() == "wal"
        assert connection.execute(text("PRAGMA foreign_keys")).scalar_one() == 1


def test_postgres_schema_name_is_checked():
    import pytest

    with pytest.raises(ValueError, match="schema name"):
        make_engine("postgresql+psycopg://postgres@127.0.0.1:5432/test", "bad; drop")


def test_migrations_match_the_models(engine):
    """Every schema change has its Alembic migration: the migrated database differs in nothing from the models."""
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    from services.db.models import Base

    with engine.connect() as connection:
        differences = compare_metadata(MigrationContext.configure(connection), Base.metadata)
    assert differences == []


def test_upgrade_from_the_first_revision_keeps_the_jobs(tmp_path):
    from alembic import command
    from alembic.config import Config

    from services.db.engine import MIGRATIONS_DIR

    engine = make_engine(f"sqlite:///{tmp_path / 'old.db'}")
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    with engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "0001")
        connection.execute(text("INSERT INTO jobs (id, kind, status, stage, fraction, attempts, params, result, "
                                "created_at, updated_at) VALUES ('old', 'scan', 'succeeded', 'done', 1, 1, '{}', "
                                "'{}', '2026-01-01', '2026-01-01')"))
    migrate(engine)
    with make_sessions(engine)() as session:
        job = session.get(Job, "old")
        assert (job.status, job.worker) == ("succeeded", None)


def test_processes_starting_at_once_migrate_an_empty_database_once():
    """The API and the workers of a deployment start together: the advisory lock lets one migrate at a time."""
    import uuid
    from concurrent.futures import ThreadPoolExecutor

    from tests.conftest import POSTGRES_URL

    schema = f"tf_race_{uuid.uuid4().hex[:10]}"
    engines = [make_engine(POSTGRES_URL, schema) for _ in range(4)]
    try:
        with ThreadPoolExecutor(len(engines)) as pool:
            list(pool.map(migrate, engines))  # re-raises the first failure
        with engines[0].connect() as connection:
            assert connection.execute(text("SELECT count(*) FROM alembic_version")).scalar_one() == 1
    finally:
        for engine in engines:
            engine.dispose()
        with make_engine(POSTGRES_URL).begin() as connection:
            connection.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))
