"""Fixtures shared across test folders: the service databases, on SQLite and on the machine's PostgreSQL."""

import uuid

import pytest
from sqlalchemy import text

from services.db.engine import make_engine, migrate

# The machine's PostgreSQL (trust auth); each test gets a fresh schema in database ``test``, dropped afterwards.
POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"


@pytest.fixture(params=["sqlite", "postgresql"])
def engine(request, tmp_path):
    """A migrated service database: SQLite in a temporary directory, then a fresh PostgreSQL schema."""
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
def small_disk(tmp_path):
    """A directory on its own tmpfs of ``size`` bytes (``mode`` "ro" for a read-only one): a full or
    read-only disk for the tests of what happens when writing fails. The machine's tests run as root."""
    import subprocess

    mounts = []

    def make(size: int, mode: str = "rw"):
        mount_point = tmp_path / f"disk{len(mounts)}"
        mount_point.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},{mode}", "tmpfs", str(mount_point)], check=True)
        mounts.append(mount_point)
        return mount_point

    yield make
    for mount_point in mounts:
        subprocess.run(["umount", "-l", str(mount_point)], check=False)
