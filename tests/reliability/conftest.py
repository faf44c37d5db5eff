"""Private instances of the machine's servers for fault tests: a PostgreSQL cluster, a Mosquitto broker
and a RabbitMQ node of the test's own, on free ports, which the test may stop and start without disturbing the
shared servers that other tests use."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

import dramatiq
import pytest

PG_BIN = Path("/usr/lib/postgresql") / sorted(p.name for p in Path("/usr/lib/postgresql").iterdir())[-1] / "bin"


@pytest.fixture(autouse=True)
def restore_dramatiq_broker():
    """Put back dramatiq's global broker: the fault tests make their own, and declare stand-in actors on it
    under the service's actor names, which ``workers.actors`` would collide with when imported later."""
    previous = dramatiq.broker.global_broker
    yield
    dramatiq.broker.global_broker = previous


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_for_port(port: int, up: bool = True, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                if up:
                    return
        except OSError:
            if not up:
                return
        time.sleep(0.1)
    raise AssertionError(f"port {port} did not go {'up' if up else 'down'} within {timeout_s} s")


class PrivatePostgres:
    """``initdb`` + ``pg_ctl`` as the postgres user in a temporary directory (trust auth, loopback only)."""

    def __init__(self) -> None:
        # Not under pytest's tmp_path: the postgres user cannot enter root's private directories.
        self.directory, self.port = Path(tempfile.mkdtemp(prefix="thermofield-pg-")), free_port()
        self.data = self.directory / "data"
        self.directory.chmod(0o755)
        shutil.chown(self.directory, "postgres", "postgres")
        self._as_postgres(PG_BIN / "initdb", "-D", self.data, "-A", "trust", "-U", "postgres", "--no-sync")
        self.url = f"postgresql+psycopg://postgres@127.0.0.1:{self.port}/postgres"

    def _as_postgres(self, *command) -> None:
        subprocess.run(["runuser", "-u", "postgres", "--", *map(str, command)], check=True, capture_output=True,
                       timeout=120)

    def start(self) -> None:
        self._as_postgres(PG_BIN / "pg_ctl", "-D", self.data, "-l", self.directory / "log", "-w", "-o",
                          f"-p {self.port} -k {self.directory} -c listen_addresses=127.0.0.1 -c fsync=off", "start")
        wait_for_port(self.port)

    def stop(self) -> None:
        self._as_postgres(PG_BIN / "pg_ctl", "-D", self.data, "-m", "immediate", "-w", "stop")
        wait_for_port(self.port, up=False)


@pytest.fixture
def private_postgres():
    server = PrivatePostgres()
    server.start()
    try:
        yield server
    finally:
        subprocess.run(["runuser", "-u", "postgres", "--", str(PG_BIN / "pg_ctl"), "-D", str(server.data), "-m",
                        "immediate", "stop"], capture_output=True, timeout=60)
        shutil.rmtree(server.directory, ignore_errors=True)


class PrivateMosquitto:
    """A ``mosquitto`` of the test's own. It persists its sessions, subscriptions, queued messages and retained
    messages to its directory when stopped (SIGTERM, as its service manager does), so a subscriber's persistent
    session outlives a restart, as on a production broker; :meth:`kill` crashes it instead (nothing saved)."""

    def __init__(self, directory: Path) -> None:
        self.port = free_port()
        self.config = directory / "mosquitto.conf"
        directory.mkdir(parents=True, exist_ok=True)
        self.config.write_text(f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence true\n"
                               f"persistence_location {directory}/\nautosave_interval 0\nuser root\n")
        self.process: subprocess.Popen | None = None

    def start(self) -> None:
        self.process = subprocess.Popen(["mosquitto", "-c", str(self.config)], stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL)
        wait_for_port(self.port)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(10)
        wait_for_port(self.port, up=False)

    def kill(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)
        wait_for_port(self.port, up=False)


@pytest.fixture
def private_mosquitto(tmp_path):
    broker = PrivateMosquitto(tmp_path / "mosquitto")
    broker.start()
    try:
        yield broker
    finally:
        broker.kill()


RABBITMQ_BIN = Path("/usr/lib/rabbitmq/bin")


class PrivateRabbitmq:
    """A RabbitMQ node of the test's own: its own node name, AMQP and distribution ports, database, logs,
    configuration and Erlang cookie (HOME) in a temporary directory. Its database survives a stop, so
    durable queues and persistent messages are there again after a restart, as on a real server."""

    def __init__(self, directory: Path) -> None:
        self.directory, self.port = directory, free_port()
        directory.mkdir(parents=True, exist_ok=True)
        self.node = f"tf{self.port}@localhost"
        (directory / "rabbitmq.conf").write_text(f"listeners.tcp.local = 127.0.0.1:{self.port}\n")
        (directory / "enabled_plugins").write_text("[].\n")
        (directory / "rabbitmq-env.conf").write_text("")
        self.env = {"PATH": f"{RABBITMQ_BIN}:/usr/sbin:/usr/bin:/bin", "HOME": str(directory),
                    "RABBITMQ_NODENAME": self.node, "RABBITMQ_NODE_PORT": str(self.port),
                    "RABBITMQ_DIST_PORT": str(free_port()), "RABBITMQ_MNESIA_BASE": str(directory / "mnesia"),
                    "RABBITMQ_LOG_BASE": str(directory / "log"),
                    "RABBITMQ_ENABLED_PLUGINS_FILE": str(directory / "enabled_plugins"),
                    "RABBITMQ_CONFIG_FILE": str(directory / "rabbitmq.conf"),
                    "RABBITMQ_CONF_ENV_FILE": str(directory / "rabbitmq-env.conf"),
                    "RABBITMQ_ADVANCED_CONFIG_FILE": str(directory / "advanced.config"),
                    "RABBITMQ_PID_FILE": str(directory / "rabbitmq.pid"), "ERL_EPMD_ADDRESS": "127.0.0.1"}
        self.url = f"amqp://guest:guest@127.0.0.1:{self.port}"
        self.process: subprocess.Popen | None = None

    def _ctl(self, *arguments: str) -> None:
        subprocess.run([str(RABBITMQ_BIN / "rabbitmqctl"), "-n", self.node, *arguments], env=self.env, check=True,
                       capture_output=True, timeout=120)

    def start(self) -> None:
        with open(self.directory / "server.log", "ab") as log:
            self.process = subprocess.Popen([str(RABBITMQ_BIN / "rabbitmq-server")], env=self.env, stdout=log,
                                            stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                            start_new_session=True)
        self._ctl("wait", str(self.directory / "rabbitmq.pid"), "--timeout", "90")
        wait_for_port(self.port)

    def stop(self) -> None:
        """Stop the node as its service would (``rabbitmqctl stop``): every connection to it drops."""
        if self.process is not None and self.process.poll() is None:
            self._ctl("stop")
            self.process.wait(60)
        wait_for_port(self.port, up=False)

    def kill(self) -> None:
        """Crash the node: SIGKILL to its processes (never to the machine's shared ``epmd``)."""
        import psutil

        root = psutil.Process(self.process.pid)
        for process in [*root.children(recursive=True), root]:
            try:  # a child may exit between being listed and being looked at
                if process.name() != "epmd":
                    process.kill()
            except psutil.NoSuchProcess:
                pass
        self.process.wait(60)
        wait_for_port(self.port, up=False)


@pytest.fixture
def private_rabbitmq(tmp_path):
    node = PrivateRabbitmq(tmp_path / "rabbitmq")
    node.start()
    try:
        yield node
    finally:
        if node.process is not None and node.process.poll() is None:
            try:
                node.stop()
            except (subprocess.SubprocessError, AssertionError):
                os.killpg(node.process.pid, signal.SIGKILL)
