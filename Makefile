# thermofield: the two set-up commands are `make demo` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
DEMO_DIR ?= demo-output

.PHONY: install install-test demo test test-reliability clean docker-compose system-libraries

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml | system-libraries
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e .
	touch $@

install-test: $(VENV)/.installed-test

$(VENV)/.installed-test: pyproject.toml | system-libraries
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(VENV)/.installed $@

demo: install
	$(BIN)/thermofield demo --data-dir $(DEMO_DIR)

test: install-test docker-compose
	$(BIN)/python -m pytest

# Open3D (the inspection's meshes and distance queries) loads libusb, libGL and libEGL from the system.
system-libraries:
	ldconfig -p | grep -q 'libusb-1.0.so.0' && ldconfig -p | grep -q 'libEGL.so.1' || { apt-get update -qq && apt-get install -y -qq --no-install-recommends libusb-1.0-0 libegl1 libgl1 libx11-6; }

# Load, soak and the long Schemathesis run (docs/reliability.md); figures go to reliability-output/.
RELIABILITY_OUT ?= reliability-output
test-reliability: install-test
	THERMOFIELD_RELIABILITY_OUT=$(abspath $(RELIABILITY_OUT)) THERMOFIELD_SCHEMATHESIS_EXAMPLES=100 \
		$(BIN)/python -m pytest -m 'reliability or schemathesis' -p no:cacheprovider -s \
		tests/api/test_schemathesis.py tests/integration/test_load.py

# tests/docker validates docker/compose.yaml with Debian's docker-compose (no Docker engine needed).
docker-compose:
	command -v docker-compose >/dev/null || { apt-get update -qq && apt-get install -y -qq --no-install-recommends docker-compose; }

clean:
	rm -rf $(VENV) $(DEMO_DIR)
