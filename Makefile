# The two commands a user needs on a fresh clone: `make demo` and `make test` (`make test-all` for every test).
# Both create the virtual environment when it is missing.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup demo test test-all lint clean

setup: $(STAMP)

# torch first, pinned, so the CPU wheel is used and nothing pulls a CUDA build;
# then the package with its dev extras and Ray (editable, so robots/ stays next to it; the fleet's tests run on a
# local Ray instance they start and stop themselves).
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q torch==2.13.0
	$(BIN)/python -m pip install -q -e '.[dev,fleet]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/torchcal demo --out runs/demo

lint: $(STAMP)
	$(BIN)/ruff check torchcal tests scripts experiments setup.py
	$(BIN)/ruff format --check torchcal tests scripts experiments setup.py

# two workers: the suite is hundreds of small single-threaded fits, and a second process uses the second core; every
# test is independent of the others' process. worksteal: a worker that runs out takes the other's queued tests, so
# the long ones near the end do not leave a core idle
# two tiers: `make test` skips the tests marked slow (the long end-to-end runs, the real-data studies, Ray, the wheel,
# the tutorial's commands) and is what a change runs first; `make test-all` runs every test, as CI does
test: $(STAMP) lint
	$(BIN)/python -m pytest -q -n 2 --dist worksteal -m "not slow"

test-all: $(STAMP) lint
	$(BIN)/python -m pytest -q -n 2 --dist worksteal

clean:
	rm -rf runs build *.egg-info .pytest_cache
