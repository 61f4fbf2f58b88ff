# The two commands a newcomer runs: `make demo` and `make test`.
# Each builds .venv on first use, and again when pyproject.toml changes or the
# extension's source does (pip builds mavest.estimator._online beside its source).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint clean

$(STAMP): pyproject.toml setup.py mavest/estimator/_online.pyx
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

# the simulated vehicle is an ArduPilot one, so its configuration
demo: $(STAMP)
	$(BIN)/mavest demo --config configs/ardupilot.toml

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/python -m pytest

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache .hypothesis
