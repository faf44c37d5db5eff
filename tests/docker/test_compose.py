"""The compose files: valid for docker-compose, and running the same commands and settings as the plain processes."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.cli.main import build_parser
from services.settings import Settings

DOCKER = Path(__file__).resolve().parents[2] / "docker"
COMPOSE = DOCKER / "compose.yaml"
OAK_OVERRIDE = DOCKER / "compose.oak.yaml"
THERMOFIELD_SERVICES = ("api", "worker", "gateway")


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def test_every_part_of_the_deployment_is_a_service(compose):
    assert set(compose["services"]) == {"api", "worker", "gateway", "rerun", "postgres", "rabbitmq", "mosquitto"}
    assert compose["services"]["worker"]["scale"] >= 2


@pytest.mark.parametrize("service", THERMOFIELD_SERVICES)
def test_services_run_real_thermofield_commands(compose, service):
    command = compose["services"][service]["command"]
    assert command[0] == service
    args = build_parser().parse_args(command)
    assert callable(args.handler)


@pytest.mark.parametrize("path", [COMPOSE, OAK_OVERRIDE])
def test_every_thermofield_variable_is_a_setting(path):
    services = yaml.safe_load(path.read_text())["services"]
    variables = {name for service in services.values() for name in service.get("environment", {})
                 if name.startswith("THERMOFIELD_")}
    assert variables
    published = {"THERMOFIELD_API_PUBLISH", "THERMOFIELD_RERUN_PUBLISH", "THERMOFIELD_MQTT_PUBLISH"}
    unknown = {name for name in variables - published if name.removeprefix("THERMOFIELD_").lower()
               not in Settings.model_fields}
    assert not unknown, f"{path.name} sets variables no setting reads: {sorted(unknown)}"


def test_proxy_and_ports_are_published_on_loopback_by_default(compose):
    services = compose["services"]
    assert services["rerun"]["entrypoint"] == ["rerun-proxy"]
    assert "--serve-grpc" in services["rerun"]["command"]
    for service in ("api", "rerun", "mosquitto"):
        for port in services[service]["ports"]:
            assert ":-127.0.0.1:" in port, f"{service} publishes {port} beyond the host by default"


def test_the_image_installs_the_rerun_proxy_and_runs_thermofield():
    dockerfile = (DOCKER / "Dockerfile").read_text()
    assert 'ENTRYPOINT ["thermofield"]' in dockerfile
    assert "/usr/local/bin/rerun-proxy" in dockerfile
    ignored = (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
    for copied in ("services/", "api/", "workers/", "device_gateway/", "migrations/"):
        assert f"!{copied}" in ignored


@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, OAK_OVERRIDE]], ids=["compose", "compose+oak"])
def test_docker_compose_accepts_the_files(files):
    binary = shutil.which("docker-compose")
    assert binary is not None, "docker-compose is not installed: run the suite with `make test`, which installs it"
    arguments = [item for path in files for item in ("-f", str(path))]
    result = subprocess.run([binary, *arguments, "config", "--quiet"], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
