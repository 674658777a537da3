# The README's commands. Each bootstraps .venv on a fresh machine.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
BENCH ?=

.PHONY: test demo bench lint typecheck pytest mosquitto chromium compose clean

$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@echo "==> installing the project with its dev extras into $(VENV)"
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

lint: $(STAMP)
	@echo "==> ruff"
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	@echo "==> import-linter (the layering: [tool.importlinter] in pyproject.toml)"
	$(VENV)/bin/lint-imports

typecheck: $(STAMP)
	@echo "==> mypy"
	$(VENV)/bin/mypy

# The MQTT transport's tests start their own mosquitto broker, and the MQTT input's tests
# publish with mosquitto_pub (a real MQTT client); install both from Debian's packages
# when missing (idempotent: nothing happens when they are already there).
mosquitto:
	@if (command -v mosquitto >/dev/null 2>&1 || test -x /usr/sbin/mosquitto) && \
		command -v mosquitto_pub >/dev/null 2>&1; then :; else \
		echo "==> installing mosquitto and its clients (the MQTT tests need a broker)"; \
		SUDO=; if [ "$$(id -u)" -ne 0 ]; then SUDO=sudo; fi; \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq \
			mosquitto mosquitto-clients >/dev/null; \
	fi

# The operator console's browser test drives Debian's chromium through Playwright (never a
# browser Playwright downloads); install it when it is missing (idempotent).
chromium:
	@if test -x /usr/bin/chromium; then :; else \
		echo "==> installing chromium (the operator console's browser test needs it)"; \
		SUDO=; if [ "$$(id -u)" -ne 0 ]; then SUDO=sudo; fi; \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq chromium >/dev/null; \
	fi

# The deploy tests validate the compose files with `docker-compose config` (no engine
# needed); Debian's docker-compose when neither it nor the compose plugin is there.
compose:
	@if command -v docker-compose >/dev/null 2>&1 || docker compose version >/dev/null 2>&1; then :; else \
		echo "==> installing docker-compose (the deploy tests validate the compose files)"; \
		SUDO=; if [ "$$(id -u)" -ne 0 ]; then SUDO=sudo; fi; \
		$$SUDO apt-get update -qq && \
		DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq docker-compose >/dev/null; \
	fi

# The tests run in three worker processes (pytest-xdist) on two cores: most of them wait
# (worlds in real time, leases, bounded waits for events), so a third keeps the cores busy;
# worksteal hands a long test's queue to an idle worker. A plain `pytest` runs them in one.
PYTEST_WORKERS ?= 3

pytest: $(STAMP) mosquitto chromium compose
	@echo "==> pytest"
	$(PY) -m pytest -q -n $(PYTEST_WORKERS) --dist worksteal

test: lint typecheck pytest

demo: $(STAMP)
	$(VENV)/bin/dyknow demo traffic

bench: $(STAMP)
	$(PY) -m bench $(BENCH)

clean:
	rm -rf $(VENV) .mypy_cache .ruff_cache .pytest_cache .hypothesis .import_linter_cache .grimp_cache
