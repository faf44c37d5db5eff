# thermofield: the two set-up commands are `make demo` and `make test`.
# Every install takes its versions from constraints.txt (refresh it with `make constraints`).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
# The first Python 3.12 that runs (pyenv's shim only answers for the version it is set to).
PYTHON312 ?= $(firstword $(foreach python,$(shell command -v python3.12) $(wildcard /root/.pyenv/versions/3.12*/bin/python3.12),\
	$(shell $(python) -c 'import sys; print(sys.executable)' 2>/dev/null)))
VENV := .venv
BIN := $(VENV)/bin
DEMO_DIR ?= demo-output
PIP_INSTALL = python -m pip install --quiet --constraint constraints.txt

.PHONY: install install-test demo test test-fast test-long test-py312 test-containers test-reliability test-soak images podman \
	constraints clean docker-compose system-libraries exiftool browser

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt | system-libraries
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/$(PIP_INSTALL) -e '.[gateway]'
	touch $@

install-test: $(VENV)/.installed-test

$(VENV)/.installed-test: pyproject.toml constraints.txt | system-libraries exiftool
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/$(PIP_INSTALL) -e '.[test,gateway,containers]'
	touch $(VENV)/.installed $@

demo: install
	$(BIN)/thermofield demo --data-dir $(DEMO_DIR)

# The suite on TEST_WORKERS processes (pytest-xdist); each takes a whole test file at a time, so a file's
# module-scoped servers are started once. Much of the suite waits on servers and subprocesses, so two processes
# take 9 minutes where one takes about 25 on this 2-core machine (docs/reliability.md).
TEST_WORKERS ?= 2
test: install-test docker-compose browser
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist loadfile

# Open3D (the inspection's meshes and distance queries) loads libusb, libGL and libEGL from the system. The
# GenICam driver (device_gateway/drivers/genicam.py) needs Aravis 0.8's introspection data, its fake GigE Vision
# camera for the tests (aravis-tools), arv-tool-0.8 that lists cameras (aravis-tools-cli), and what PyGObject
# builds against (gobject-introspection, cairo, pkg-config).
GENICAM_PACKAGES := gir1.2-aravis-0.8 aravis-tools aravis-tools-cli libgirepository1.0-dev libcairo2-dev pkg-config
system-libraries:
	ldconfig -p | grep -q 'libusb-1.0.so.0' && ldconfig -p | grep -q 'libEGL.so.1' || { apt-get update -qq && apt-get install -y -qq --no-install-recommends libusb-1.0-0 libegl1 libgl1 libx11-6; }
	dpkg-query -W -f='$${Status}\n' $(GENICAM_PACKAGES) 2>/dev/null | grep -c 'install ok installed' \
		| grep -qx '$(words $(GENICAM_PACKAGES))' || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
		apt-get install -y -qq --no-install-recommends $(GENICAM_PACKAGES); }

# Debian's Chromium, which the demo's test opens the web viewer in through Playwright (Playwright's own
# browser download needs the internet).
browser:
	command -v chromium >/dev/null || { apt-get update -qq && apt-get install -y -qq --no-install-recommends chromium; }

# ExifTool: the tests check the FLIR radiometric JPEG reader against FLIR's model computed from its tags
# (tests/formats/test_flir.py); thermofield itself reads the files with flyr.
exiftool:
	command -v exiftool >/dev/null || { apt-get update -qq && apt-get install -y -qq --no-install-recommends libimage-exiftool-perl; }

# The load, the long Schemathesis run and the long fault tests, the scaled-out worker crash among them, and the hostile
# input (docs/reliability.md); figures go to reliability-output/ (the hostile-input table: hostile.md).
# The 10-minute soak is `make test-soak` (about 12 min with its start and warm-up); `.ci/run` runs it last.
RELIABILITY_OUT ?= reliability-output
test-reliability: install-test
	THERMOFIELD_RELIABILITY_OUT=$(abspath $(RELIABILITY_OUT)) THERMOFIELD_SCHEMATHESIS_EXAMPLES=100 \
		$(BIN)/python -m pytest -m 'reliability or schemathesis' -k 'not soak' -p no:cacheprovider -s \
		tests/api/test_schemathesis.py tests/integration/test_load.py tests/integration/test_station_faults.py \
		tests/reliability/test_faults.py tests/reliability/test_hostile.py tests/integration/test_scaled_out.py \
		tests/integration/test_station_service.py \
		tests/device_gateway/test_genicam_gigevision.py

# The longest checks of documented figures beyond the issues' targets (the `long` marker; .ci/run runs them).
test-long: install-test
	$(BIN)/python -m pytest -m long -p no:cacheprovider

test-soak: install-test
	THERMOFIELD_RELIABILITY_OUT=$(abspath $(RELIABILITY_OUT)) THERMOFIELD_SOAK_SECONDS=600 \
		$(BIN)/python -m pytest -m reliability -k soak -p no:cacheprovider -s tests/integration/test_load.py

# The service's tests on Python 3.12, in a venv of its own (.venv-py312); PY312_TESTS=tests runs them all.
PY312_TESTS ?= tests/db tests/api tests/formats tests/workers tests/device_gateway/test_oak.py tests/test_packaging.py
test-py312: .venv-py312/.installed-test
	.venv-py312/bin/python -m pytest -q -p no:cacheprovider $(PY312_TESTS)

.venv-py312/.installed-test: pyproject.toml constraints.txt | system-libraries exiftool
	test -n "$(PYTHON312)" || { echo "make test-py312: no python3.12 on PATH"; exit 2; }
	test -x .venv-py312/bin/python || $(PYTHON312) -m venv .venv-py312
	.venv-py312/bin/$(PIP_INSTALL) -e '.[test,gateway]'
	touch $@

# The whole compose stack in podman on this machine (docs/deployment.md): images built from a debootstrap
# base (cached in podman's store), then tests/containers starts it, scans, kills a worker and tears it down.
test-containers: install-test podman images
	$(BIN)/python -m pytest -m containers -p no:cacheprovider tests/containers

images: podman
	docker/local/build-images.sh

podman:
	@command -v podman >/dev/null && command -v runc >/dev/null && command -v debootstrap >/dev/null \
		&& command -v iptables >/dev/null || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
		apt-get install -y -qq --no-install-recommends podman runc debootstrap iptables netavark aardvark-dns; }

# Re-resolve every dependency of every extra to the newest versions the bounds in pyproject.toml allow.
constraints:
	rm -rf .venv-constraints && $(PYTHON) -m venv .venv-constraints
	.venv-constraints/bin/python -m pip install --quiet ".[$$($(PYTHON) docker/requirements.py --extras)]" 'setuptools>=69'
	{ echo "# Pinned versions of every dependency of thermofield and its extras (pip constraints)."; \
	  echo "# Refresh: make constraints (resolved with $$(.venv-constraints/bin/python --version))."; \
	  .venv-constraints/bin/python -m pip freeze --all --exclude thermofield --exclude pip; } > constraints.txt
	rm -rf .venv-constraints

# The unit tier alone: no servers, no PostgreSQL.
test-fast: install-test
	$(BIN)/python -m pytest -m "unit and not postgres and not containers and not reliability"

# tests/docker validates docker/compose.yaml with Debian's docker-compose (no Docker engine needed).
docker-compose:
	command -v docker-compose >/dev/null || { apt-get update -qq && apt-get install -y -qq --no-install-recommends docker-compose; }

clean:
	rm -rf $(VENV) .venv-py312 $(DEMO_DIR)
