# Two commands set up everything on a fresh machine:
#   make demo   - create .venv and run the main job (two robots sharing maps)
#   make test   - create .venv with test extras, install socat and chromium if missing, lint, run pytest
# The torch wheel on this machine is built for CPython 3.11, so prefer that interpreter.
PY ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
# pip finds the CPU torch build on local disk; constraints.txt pins it so nothing pulls CUDA.
FIND_LINKS := $(if $(wildcard /opt/wheels),--find-links /opt/wheels)
PYTEST_ARGS ?=

.PHONY: demo test lint venv socat chromium clean

venv: $(STAMP)

$(BIN)/python:
	@$(PY) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "mapd needs Python 3.11 or newer")'
	$(PY) -m venv $(VENV)

$(STAMP): pyproject.toml constraints.txt | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -c constraints.txt $(FIND_LINKS) -e '.[test]'
	@touch $@

socat:
	@command -v socat >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing socat (serial-link tests use socat pty pairs)"; \
	    (apt-get install -y -qq socat >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq socat)); \
	  else \
	    echo "socat is missing; install it with: sudo apt-get install -y socat"; exit 1; \
	  fi; }

# The live view's browser tests use Debian's headless chromium; without it they skip, saying so.
chromium:
	@command -v chromium >/dev/null 2>&1 || { \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then \
	    echo "installing chromium (the live view's browser tests use it headless)"; \
	    (apt-get install -y -qq chromium >/dev/null 2>&1 || (apt-get update -qq && apt-get install -y -qq chromium >/dev/null 2>&1)) \
	      || echo "chromium could not be installed: the browser tests will be skipped"; \
	  else \
	    echo "chromium is missing (sudo apt-get install -y chromium): the browser tests will be skipped"; \
	  fi; }

lint: $(STAMP)
	$(BIN)/ruff check mapd transports tests
	$(BIN)/ruff format --check mapd transports tests
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache

# Three workers on CI's two cores: many tests wait on real clocks (radio turns, daemons' periods),
# and a third worker uses time two would leave idle (measured here: 455-467 s with two, 360-440 s with three).
# The lossless codec's numba kernels are compiled once, before the workers start: on a fresh clone
# each worker, and each daemon a test starts, would otherwise compile them at the same time.
# Work stealing: tests last from milliseconds to 40 s, and with xdist's default split a worker
# left with a batch of long ones set the end (measured here, same tree: 473 s against 504 s).
test: $(STAMP) socat chromium lint
	$(BIN)/mapd warmup --codec lossless
	$(BIN)/pytest -n 3 --dist worksteal $(PYTEST_ARGS)

demo: $(STAMP)
	$(BIN)/mapd demo

clean:
	rm -rf $(VENV) out .pytest_cache .mypy_cache .ruff_cache
