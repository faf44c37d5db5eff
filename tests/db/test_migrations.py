"""Migrations on SQLite and PostgreSQL: from empty to head, down to empty and up again, the schema then equal to
the models' (alembic's compare_metadata: tables, columns, types, nullability, defaults, indexes, keys); an upgrade
from the first revision with rows in every table keeps them."""

import uuid

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect, text

from services.db.engine import MIGRATIONS_DIR, make_engine, run_alembic
from services.db.models import Base

POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


@pytest.fixture(params=["sqlite", "postgresql"])
def empty_engine(request, tmp_path):
    """An engine on an empty database: a new SQLite file, or a new PostgreSQL schema."""
    if request.param == "sqlite":
        engine = make_engine(f"sqlite:///{tmp_path / 'empty.db'}")
        yield engine
        engine.dispose()
        return
    schema = f"tf_mig_{uuid.uuid4().hex[:12]}"
    engine = make_engine(POSTGRES_URL, schema)
    yield engine
    engine.dispose()
    with make_engine(POSTGRES_URL).begin() as connection:
        connection.execute(text(f"DROP SCHEMA {schema} CASCADE"))


def _alembic(engine, action, revision):
    run_alembic(engine, action, revision)


def _tables(engine) -> set[str]:
    inspector = inspect(engine)
    return set(inspector.get_table_names()) - {"alembic_version"}


def _differences_from_the_models(engine) -> list:
    """What ``alembic revision --autogenerate`` would write: every difference between the database's schema and
    the models' metadata (columns with their types and server defaults, indexes, unique constraints, foreign keys)."""
    with engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True, "compare_server_default": True})
        return compare_metadata(context, Base.metadata)


def test_upgrade_from_empty_downgrade_and_upgrade_again(empty_engine):
    model_tables = set(Base.metadata.tables)
    revisions = [script.revision for script in ScriptDirectory(str(MIGRATIONS_DIR)).walk_revisions()]
    assert len(revisions) >= 3
    _alembic(empty_engine, "upgrade", "head")
    assert _tables(empty_engine) == model_tables
    assert _differences_from_the_models(empty_engine) == []
    for revision in revisions[1:]:  # one step down at a time, each one exercised
        _alembic(empty_engine, "downgrade", revision)
    _alembic(empty_engine, "downgrade", "base")
    assert _tables(empty_engine) == set()
    _alembic(empty_engine, "upgrade", "head")
    assert _tables(empty_engine) == model_tables
    assert _differences_from_the_models(empty_engine) == []  # the downgrades left nothing behind to collide with


def test_the_schema_comparison_sees_a_missing_index(empty_engine):
    """The comparison above can fail: an index dropped from the database is reported."""
    _alembic(empty_engine, "upgrade", "head")
    index = next(index for table in Base.metadata.sorted_tables for index in table.indexes)
    with empty_engine.begin() as connection:
        connection.execute(text(f"DROP INDEX {index.name}"))
    kinds = {difference[0] for difference in _differences_from_the_models(empty_engine)}
    assert "add_index" in kinds, kinds


def test_an_upgrade_with_data_in_every_table_keeps_it(empty_engine):
    _alembic(empty_engine, "upgrade", "0001")
    stamp = "'2026-01-01 00:00:00+00'"
    with empty_engine.begin() as connection:
        for statement in (
            f"INSERT INTO api_keys VALUES ('k1', 'mes', '{'a' * 64}', 'operate', {stamp}, NULL)",
            "INSERT INTO jobs (id, kind, status, stage, fraction, attempts, params, result, created_at, updated_at) "
            f"VALUES ('j1', 'scan', 'succeeded', 'done', 1, 1, '{{\"scan_id\": \"s1\"}}', '{{\"n\": 3}}', {stamp}, "
            f"{stamp})",
            "INSERT INTO calibration_sets (id, name, station, rig_sha256, active, source, job_id, created_at) "
            f"VALUES ('c1', 'rig', 'station1', '{'b' * 64}', true, 'upload', NULL, {stamp})",
            "INSERT INTO scans VALUES ('s1', 'station1', 'j1', 'c1', 'part-7', '{\"field.ply\": \"x\"}', "
            f"'{{\"point_count\": 5}}', {stamp})",
            "INSERT INTO idempotency_records (api_key_id, key, request_sha256, status_code, location, body, created_at) "
            f"VALUES ('k1', 'retry-1', '{'c' * 64}', 202, '/v1/jobs/j1', '{{}}', {stamp})",
        ):
            connection.execute(text(statement))
    _alembic(empty_engine, "upgrade", "head")
    with empty_engine.connect() as connection:
        def rows(query):
            return [tuple(row) for row in connection.execute(text(query))]

        assert rows("SELECT id, scopes FROM api_keys") == [("k1", "operate")]
        assert rows("SELECT id, status, attempts, worker FROM jobs") == [("j1", "succeeded", 1, None)]
        # 0005 (the outbox): a job from before it had been sent when it was created, so it is not sent again
        assert rows("SELECT count(*) FROM jobs WHERE dispatched_at = created_at") == [(1,)]
        assert rows("SELECT id, station, active FROM calibration_sets") == [("c1", "station1", True)]
        assert rows("SELECT id, part_id, job_id, part_type_id, verdict FROM scans") == [("s1", "part-7", "j1", None,
                                                                                        None)]
        assert rows("SELECT key, status_code, location FROM idempotency_records") == [("retry-1", 202, "/v1/jobs/j1")]


def test_part_types_down_to_0003_keeps_the_scans_and_up_again_takes_new_ones(empty_engine):
    """0004 adds the part types and the scans' inspection; going down keeps every scan, without those."""
    _alembic(empty_engine, "upgrade", "head")
    stamp = "'2026-01-01 00:00:00+00'"
    with empty_engine.begin() as connection:
        for statement in (
            "INSERT INTO jobs (id, kind, status, stage, fraction, attempts, params, result, created_at, updated_at) "
            f"VALUES ('j1', 'scan', 'succeeded', 'done', 1, 1, '{{}}', '{{}}', {stamp}, {stamp})",
            "INSERT INTO calibration_sets (id, name, station, rig_sha256, active, source, created_at) "
            f"VALUES ('c1', 'rig', 'station1', '{'b' * 64}', true, 'upload', {stamp})",
            "INSERT INTO part_types (id, name, station, material, part_sha256, mesh_sha256, selected, created_at) "
            f"VALUES ('p1', 'billet-90', 'station1', 'carbon-steel', '{'d' * 64}', '{'e' * 64}', true, {stamp})",
            "INSERT INTO scans (id, station, job_id, calibration_set_id, part_id, part_type_id, verdict, features, "
            f"artifacts, created_at) VALUES ('s1', 'station1', 'j1', 'c1', 'part-7', 'p1', 'NotOK', "
            f"'[{{\"name\": \"body_diameter\"}}]', '{{}}', {stamp})",
        ):
            connection.execute(text(statement))
    with pytest.raises(Exception):  # the scan's part type must exist
        with empty_engine.begin() as connection:
            connection.execute(text("UPDATE scans SET part_type_id = 'nowhere'"))
    _alembic(empty_engine, "downgrade", "0003")
    assert "part_types" not in _tables(empty_engine)
    with empty_engine.connect() as connection:
        assert [tuple(row) for row in connection.execute(text("SELECT id, part_id FROM scans"))] == [("s1", "part-7")]
        assert "verdict" not in {column["name"] for column in inspect(connection).get_columns("scans")}
    _alembic(empty_engine, "upgrade", "head")
    with empty_engine.connect() as connection:
        assert [tuple(row) for row in connection.execute(text("SELECT id, verdict FROM scans"))] == [("s1", None)]
