"""The package as a plant installs it: constraints that pin every dependency, and a wheel that runs on its own."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import sysconfig
import time
import tomllib
import uuid
import zipfile
from pathlib import Path

import httpx
import pytest
from sqlalchemy import text

from services.db.engine import make_engine

ROOT = Path(__file__).resolve().parents[1]
POSTGRES_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/test"
BROKER_URL = "amqp://guest:guest@127.0.0.1:5672"


def _name(requirement: str) -> str:
    return re.sub(r"[-_.]+", "-", re.match(r"[A-Za-z0-9][A-Za-z0-9._-]*", requirement).group()).lower()


def test_the_constraints_pin_every_dependency_of_every_extra():
    """Every requirement this platform installs (a requirement marked for other platforms, e.g. open3d where
    open3d-cpu is used, is resolved only there)."""
    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    lines = project["dependencies"] + [line for extra in project["optional-dependencies"].values() for line in extra]
    required = {_name(line) for line in lines
                if Requirement(line).marker is None or Requirement(line).marker.evaluate({"extra": ""})}
    pinned = {_name(line): line.split("==", 1)[1] for line in (ROOT / "constraints.txt").read_text().splitlines()
              if line and not line.startswith("#")}
    missing = sorted(required - set(pinned))
    assert not missing, f"constraints.txt does not pin {missing}: run `make constraints`"


def test_the_images_leave_the_gateway_extra_out_of_the_api_and_worker():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = {_name(line) for line in project["dependencies"]}
    assert {"depthai", "pygame-ce"} <= {_name(line) for line in project["optional-dependencies"]["gateway"]}
    assert not base & {"depthai", "pygame", "pygame-ce", "opencv-contrib-python-headless"}


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--wheel-dir", str(out), str(ROOT)],
                   check=True, timeout=300, capture_output=True)
    return next(out.glob("thermofield-*.whl"))


def test_the_wheel_carries_the_migrations(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert "services/db/migrations/env.py" in names
    assert "services/db/migrations/script.py.mako" in names
    shipped = {Path(name).name for name in names if name.startswith("services/db/migrations/versions/")}
    in_tree = {path.name for path in (ROOT / "services/db/migrations/versions").glob("*.py")}
    assert shipped == in_tree


def test_the_wheel_carries_the_machine_vision_nodeset(wheel):
    """The OPC Foundation's NodeSet the OPC UA server loads (docs/opcua.md), whole, with its licence notice."""
    shipped = zipfile.ZipFile(wheel).read("services/opcua/Opc.Ua.MachineVision.NodeSet2.xml")
    assert shipped == (ROOT / "services/opcua/Opc.Ua.MachineVision.NodeSet2.xml").read_bytes()
    assert b"OPC Foundation MIT License" in shipped


def test_an_installed_wheel_serves_the_api_on_an_empty_database(wheel, tmp_path):
    """A fresh venv holding the wheel alone (its dependencies come from this interpreter's site-packages, after
    it on the path), run outside the checkout: `thermofield api` migrates an empty database and serves."""
    schema = f"tf_wheel_{uuid.uuid4().hex[:10]}"
    port = _free_port()
    env = {name: value for name, value in os.environ.items() if name not in ("PYTHONPATH", "VIRTUAL_ENV")} | {
        "THERMOFIELD_DATABASE_URL": POSTGRES_URL, "THERMOFIELD_DATABASE_SCHEMA": schema,
        "THERMOFIELD_BROKER_URL": BROKER_URL, "THERMOFIELD_JOB_QUEUE": f"tf-wheel-{schema}",
        "THERMOFIELD_API_PORT": str(port), "THERMOFIELD_MQTT_HOST": "", "THERMOFIELD_DATA_DIR": str(tmp_path),
    }
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120, env=env)
    python = venv / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                    "--no-index", "--ignore-installed", str(wheel)], check=True, timeout=120, capture_output=True,
                   env=env, cwd=tmp_path)
    site = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True, env=env).stdout.strip())
    (site / "zz_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    where = subprocess.run([str(python), "-c", "import services.db.engine as e; print(e.MIGRATIONS_DIR)"],
                           env=env, cwd=tmp_path, check=True, capture_output=True, text=True).stdout.strip()
    assert where.startswith(str(site)), f"the migrations came from {where}, not from the installed wheel"
    api = subprocess.Popen([str(venv / "bin" / "thermofield"), "api"], env=env, cwd=tmp_path,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    try:
        _wait_ready(f"http://127.0.0.1:{port}/readyz", api)
        key = subprocess.run([str(venv / "bin" / "thermofield"), "apikey", "create", "--scopes", "read"], env=env,
                             cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert key.returncode == 0, key.stderr
        answer = httpx.get(f"http://127.0.0.1:{port}/v1/jobs", headers={"Authorization": f"Bearer {key.stdout.strip()}"})
        assert answer.status_code == 200 and answer.json() == []
    finally:
        api.terminate()
        api.wait(timeout=30)
        with make_engine(POSTGRES_URL).begin() as connection:
            connection.execute(text(f"DROP SCHEMA IF EXISTS {schema} CASCADE"))


def _free_port() -> int:
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _wait_ready(url: str, process: subprocess.Popen, timeout_s: float = 120.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"`thermofield api` exited with {process.returncode}: {process.stdout.read()[-3000:]}")
        try:
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    raise AssertionError(f"`thermofield api` was not ready at {url} within {timeout_s} s")

