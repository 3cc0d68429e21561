# The whole set-up on a fresh machine with Python 3.11 is `make sim` or `make test`:
# each creates .venv when it is missing and installs the project with its dev extras.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= runs/sim
PYTEST_ARGS ?=
# pytest-xdist workers: the suite is mostly single-threaded Python, so two halve it on 2 cores
# (0 runs it in one process).
PYTEST_WORKERS ?= 2
# Small GP matrices: threaded BLAS only adds contention (see bridge/cli/main.py).
export OPENBLAS_NUM_THREADS ?= 1
export OMP_NUM_THREADS ?= 1

.PHONY: sim test lint clean

$(BIN)/python:
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; set PYTHON=/path/to/python3.11" >&2; exit 1; }
	$(PYTHON) -m venv $(VENV)

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev,peers]'
	@touch $(STAMP)

sim: $(STAMP)
	$(BIN)/hilbo sim --minutes 60 --speed max --seed 1 --out $(OUT)

lint: $(STAMP)
	$(BIN)/ruff check .

test: $(STAMP)
	@bash scripts/ensure-uml.sh
	$(BIN)/ruff check .
	$(BIN)/lint-imports
	$(BIN)/python -m pytest -n $(PYTEST_WORKERS) $(PYTEST_ARGS)

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .hypothesis
