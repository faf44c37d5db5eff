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


@pytest.fixture(autouse=True, scope="session")
def _private_table_cache(tmp_path_factory):
    """Commands keep triangulation tables under $XDG_CACHE_HOME: the suite's go to a temporary directory
    (inherited by the commands it runs as subprocesses)."""
    import os

    previous = os.environ.get("XDG_CACHE_HOME")
    os.environ["XDG_CACHE_HOME"] = str(tmp_path_factory.mktemp("cache"))
    yield
    if previous is None:
        os.environ.pop("XDG_CACHE_HOME")
    else:
        os.environ["XDG_CACHE_HOME"] = previous


@pytest.fixture(autouse=True, scope="session")
def _no_web_viewer_by_default():
    """The services the suite starts serve no Rerun web viewer unless a test asks for one (``--rerun-web-port``,
    as the demo's test does): its default port 9090 would be one more that two services started at once share."""
    import os

    previous = os.environ.get("THERMOFIELD_RERUN_WEB_PORT")
    os.environ["THERMOFIELD_RERUN_WEB_PORT"] = ""
    yield
    if previous is None:
        os.environ.pop("THERMOFIELD_RERUN_WEB_PORT")
    else:
        os.environ["THERMOFIELD_RERUN_WEB_PORT"] = previous


def pytest_collection_modifyitems(config, items):
    """Every test gets one tier. A test file that starts processes or servers, or renders full-size simulated
    scans or runs whole calibrations and registrations (seconds per test), says so itself:
    ``pytestmark = pytest.mark.integration``; every other test is ``unit``. The PostgreSQL cases of the ``engine``
    fixture are marked ``postgres`` too (files that need the server throughout mark themselves)."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        if callspec is not None and callspec.params.get("engine") == "postgresql":
            item.add_marker(pytest.mark.postgres)
        if not item.get_closest_marker("integration"):
            item.add_marker(pytest.mark.unit)
