"""The compose files: valid for docker-compose, and running the same commands and settings as the plain processes.

tests/containers starts them for real (make test-containers)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

from services.cli.main import build_parser
from services.settings import Settings

pytestmark = pytest.mark.integration

DOCKER = Path(__file__).resolve().parents[2] / "docker"
COMPOSE = DOCKER / "compose.yaml"
OAK_OVERRIDE = DOCKER / "compose.oak.yaml"
GENICAM_OVERRIDE = DOCKER / "compose.genicam.yaml"
LOCAL_OVERRIDE = DOCKER / "compose.local.yaml"
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


def test_every_service_has_a_healthcheck_and_thermofield_checks_are_real_commands(compose):
    for name, service in compose["services"].items():
        test = service.get("healthcheck", {}).get("test")
        assert test and test[0] == "CMD", f"{name} has no healthcheck"
        if test[1] == "thermofield":
            assert callable(build_parser().parse_args(test[2:]).handler)


def test_the_public_images_are_pinned_by_digest(compose):
    pinned = re.compile(r"^\$\{THERMOFIELD_[A-Z_]+_IMAGE:-[a-z0-9./-]+:[\w.-]+@sha256:[0-9a-f]{64}\}$")
    for name in ("postgres", "rabbitmq", "mosquitto"):
        assert pinned.match(compose["services"][name]["image"]), compose["services"][name]["image"]
    assert pinned.match(compose["services"]["api"]["build"]["args"]["BASE"])


def test_the_local_variant_swaps_only_the_images(compose):
    local = yaml.safe_load(LOCAL_OVERRIDE.read_text())["services"]
    assert set(local) == set(compose["services"])
    assert all(set(service) == {"image"} and service["image"].startswith("localhost/") for service in local.values())


@pytest.mark.parametrize("path", [COMPOSE, OAK_OVERRIDE, GENICAM_OVERRIDE])
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
    assert services["rerun"]["build"]["target"] == "rerun" and "--serve-grpc" in services["rerun"]["command"]
    for service in ("api", "rerun", "mosquitto"):
        for port in services[service]["ports"]:
            assert ":-127.0.0.1:" in port, f"{service} publishes {port} beyond the host by default"


def test_one_dockerfile_builds_each_role_non_root_from_a_base_argument(compose):
    dockerfile = (DOCKER / "Dockerfile").read_text()
    assert "ARG BASE=python:3.11-slim-bookworm\n" in dockerfile
    targets = re.findall(r"^FROM \S+ AS (\w[\w-]*)$", dockerfile, flags=re.MULTILINE)
    assert {"service", "gateway", "rerun"} <= set(targets)
    assert {service["build"]["target"] for service in compose["services"].values() if "build" in service} == {
        "service", "gateway", "rerun"}
    for target in ("service", "gateway", "rerun"):
        stage = dockerfile.split(f" AS {target}\n", 1)[1].split("\nFROM ", 1)[0]
        assert "USER thermofield" in stage, f"the {target} image runs as root"
    assert dockerfile.count("-c constraints.txt") == 2  # the package's and the gateway extra's dependencies
    ignored = (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
    for copied in ("pyproject.toml", "constraints.txt", "services/", "api/", "workers/", "device_gateway/"):
        assert f"!{copied}" in ignored


@pytest.mark.parametrize("files", [[COMPOSE], [COMPOSE, OAK_OVERRIDE], [COMPOSE, GENICAM_OVERRIDE],
                                   [COMPOSE, LOCAL_OVERRIDE]],
                         ids=["compose", "compose+oak", "compose+genicam", "compose+local"])
def test_docker_compose_accepts_the_files(files):
    binary = shutil.which("docker-compose")
    assert binary is not None, "docker-compose is not installed: run the suite with `make test`, which installs it"
    arguments = [item for path in files for item in ("-f", str(path))]
    environment = {**os.environ, "THERMOFIELD_GENICAM_CAMERA": "192.168.10.21"}  # compose.genicam.yaml requires it
    result = subprocess.run([binary, *arguments, "config", "--quiet"], capture_output=True, text=True, timeout=60,
                            env=environment)
    assert result.returncode == 0, result.stderr


def test_the_api_serves_opc_ua_on_loopback_with_its_certificates_on_a_volume(compose):
    api = compose["services"]["api"]
    endpoint = api["environment"]["THERMOFIELD_OPCUA_ENDPOINT"]
    assert endpoint.startswith("opc.tcp://0.0.0.0:4840/")  # every interface of the container, published below
    assert "${THERMOFIELD_OPCUA_PUBLISH:-127.0.0.1:4840}:4840" in api["ports"]
    assert api["environment"]["THERMOFIELD_MQTT_HOST"]  # the scaled-out API hears the workers' results over MQTT
    # the server's certificate and the trusted clients (DATA_DIR/opcua, the default) survive a new container
    assert "THERMOFIELD_OPCUA_PKI_DIR" not in api["environment"] and "opcua:/data/opcua" in api["volumes"]
    assert "opcua" in compose["volumes"] and api["hostname"]  # the certificate's host name, whatever container
    assert "/data/opcua" in (DOCKER / "Dockerfile").read_text()  # owned by the image's user, as the volume then is
