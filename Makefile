# The two commands of the README: `make demo` and `make test`.
# Both create .venv when it is missing and install what they need.
#
# The interpreter is the system's own python3 when it is 3.11 or newer: the service runs
# on it (docs/operations.md makes its venv with `sudo python3 -m venv`, and sudo's PATH
# finds /usr/bin first), so the tests and the bench run what a machine runs. Until
# 2026-11-28 they ran on whatever python3 came first on PATH (this machine's: a pyenv
# 3.11.7), and five tests that fail on Debian 12's 3.11.2 went unseen
# (tests/test_patterns.py). Else the python3 on PATH; `make PY=...` for another.
SYSTEM_PY := $(shell /usr/bin/python3 -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null && echo /usr/bin/python3)
PY ?= $(or $(SYSTEM_PY),python3)
VENV := .venv
BIN := $(VENV)/bin
# Made again when pyproject.toml changes, or .venv was made by another interpreter.
PY_VERSION = $(shell $(PY) -c 'import sys; print(sys.version)' 2>/dev/null)
STAMP := $(VENV)/.installed-$(shell { cat pyproject.toml; echo '$(PY_VERSION)'; } | cksum | cut -d' ' -f1)

.PHONY: demo test lint typecheck unit clean system-deps service-test

# Debian's own python3 makes no venv without python3-venv (ensurepip): installed as root,
# else the command to run.
$(STAMP): pyproject.toml
	@if [ -x $(BIN)/python ] && [ "$$($(BIN)/python -c 'import sys; print(sys.version)')" != '$(PY_VERSION)' ]; then \
	    echo "$(VENV) was made by another python: making it again with $(PY)"; rm -rf $(VENV); fi
	@[ -x $(BIN)/python ] || { \
	    $(PY) -c 'import ensurepip' 2>/dev/null || { \
	        if [ "$$(id -u)" != 0 ]; then \
	            echo "$(PY) cannot make a virtual environment: run  sudo apt-get install python3-venv"; \
	            exit 1; fi; \
	        echo "installing python3-venv: $(PY) needs it to make .venv"; \
	        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null; }; \
	    echo "making $(VENV) with $(PY) ($(firstword $(PY_VERSION)))"; \
	    $(PY) -m venv $(VENV) && $(BIN)/pip install --quiet --upgrade pip; }
	$(BIN)/pip install --quiet -e '.[test,bench]'
	rm -f $(VENV)/.installed-*
	touch $@

demo: $(STAMP)
	$(BIN)/python -m hostd.demo $(DEMO_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check hostd tests $(wildcard bench)
	$(BIN)/ruff format --check hostd tests $(wildcard bench)

typecheck: $(STAMP)
	$(BIN)/mypy

# Most tests wait on simulated motion and real ptys rather than compute: spread over
# processes (pytest-xdist). Four, not six: with six on two cores the browser tests and
# the boards' real-time jobs starved each other (jobs underflowed, pages timed out).
# Tests are handed out one at a time, longest first (tests/conftest.py, `OneAtATime`).
# Bytecode caches are written even where the environment sets PYTHONDONTWRITEBYTECODE
# (this machine's does): without them each worker rewrote every test module's asserts
# again (8 of its 13 s of CPU to collect) and each daemon process compiled hostd again
# (docs/testing.md, "The suite's own time"). They go to __pycache__ (.gitignore).
TEST_WORKERS ?= 4
unit: $(STAMP)
	PYTHONDONTWRITEBYTECODE= $(BIN)/pytest -n $(TEST_WORKERS)

test: system-deps lint typecheck unit

# The systemd unit under a real systemd (PID 1 in a systemd-nspawn container; root only):
# tests/service. The Debian root is built once by debootstrap into /var/cache/hostd-test.
service-test: system-deps $(STAMP)
	HOSTD_SERVICE_TEST=1 $(BIN)/pytest tests/service -p no:randomly --timeout=900

# The tests run the real parts: LinuxCNC's rs274 (the G-code reference), Debian's chromium and
# its driver (the dashboard), mosquitto (MQTT) and systemd's tools (the unit; debootstrap and
# systemd-nspawn boot it under a real systemd: make service-test). Each one missing
# is installed from Debian's packages when this runs as root; otherwise it stops at once with
# the command to run. Nothing is ever skipped to get green.
SYSTEM_DEPS := rs274:linuxcnc-uspace chromium:chromium chromedriver:chromium-driver \
	mosquitto:mosquitto systemd-analyze:systemd \
	debootstrap:debootstrap systemd-nspawn:systemd-container
system-deps:
	@missing=""; for pair in $(SYSTEM_DEPS); do \
	    cmd=$${pair%%:*}; pkg=$${pair#*:}; \
	    PATH="$$PATH:/usr/sbin:/sbin" command -v $$cmd >/dev/null 2>&1 || missing="$$missing $$pkg"; \
	done; \
	[ -z "$$missing" ] && exit 0; \
	cmd="apt-get install -y --no-install-recommends$$missing"; \
	if [ "$$(id -u)" != 0 ]; then \
	    echo "make test needs Debian packages that are missing:$$missing"; \
	    echo "run:  sudo apt-get update && sudo $$cmd"; exit 1; \
	fi; \
	echo "make test: installing$$missing (the real rs274, browser, MQTT broker and systemd tools the tests run against; about 400 MB, a few minutes the first time)"; \
	apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$cmd -qq >/dev/null

clean:
	rm -rf $(VENV) .venv-3.* .pytest_cache .mypy_cache .ruff_cache

# The suite on each other Python 3.11+ this machine has, each in a .venv-<version> of its
# own: Debian 12's 3.11.2 and 3.13 each broke hostd in a way no other Python showed
# (docs/gcode.md, tests/test_docstrings.py). Not part of `make test`, whose time it
# multiplies. PYTHONS=... names them; by default every python3.1x under /usr/bin and
# /usr/local/bin and pyenv's, one of each version, the one `make test` runs left out.
PYTHONS ?= $(wildcard /usr/bin/python3.1[1-9] /usr/local/bin/python3.1[1-9] $(HOME)/.pyenv/versions/3.1[1-9]*/bin/python3)
.PHONY: test-pythons
test-pythons: $(STAMP)
	@seen="$$($(BIN)/python -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])')"; \
	for py in $(PYTHONS); do \
	    v=$$($$py -c 'import sys; print("%d.%d.%d" % sys.version_info[:3]) if sys.version_info >= (3, 11) else None' 2>/dev/null); \
	    case "$$v" in ""|None) continue;; esac; case " $$seen " in *" $$v "*) continue;; esac; \
	    seen="$$seen $$v"; echo "== Python $$v ($$py)"; \
	    [ -x .venv-$$v/bin/python ] || $$py -m venv .venv-$$v || exit 1; \
	    .venv-$$v/bin/pip install --quiet --upgrade pip && .venv-$$v/bin/pip install --quiet -e '.[test]' || exit 1; \
	    PYTHONDONTWRITEBYTECODE= .venv-$$v/bin/pytest -n $(TEST_WORKERS) || exit 1; \
	done

# Performance figures beside their baselines (bench/run.py); BENCH_ARGS=--quick to try things.
# docs/openrpc.json: the API's OpenRPC document, as `rpc.discover` serves it (made from the
# method table: hostd/api/openrpc.py). A test fails while the file is not up to date.
.PHONY: openrpc
openrpc: $(STAMP)
	$(BIN)/python -m hostd.api.openrpc docs/openrpc.json

.PHONY: bench soak
bench: $(STAMP)
	$(BIN)/python -m bench $(BENCH_ARGS)

# Long fault runs, not part of `make test`: against the daemon process (bench/soak.py),
# unplug/re-plug and alarm cycles over real ptys (bench/soak_link.py), and the
# model-based test (tests/stateful) with many more, longer, random examples, and the
# whole suite once more on asyncio's own loop (`make test` runs on the default, uvloop).
soak: $(STAMP)
	$(BIN)/python -m bench.soak $(SOAK_ARGS)
	$(BIN)/python -m bench.soak_link
	HOSTD_STATEFUL_PROFILE=soak $(BIN)/pytest tests/stateful --timeout=0
	HOSTD_TEST_LOOP=asyncio $(BIN)/pytest
