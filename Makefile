# Two entry points do all the set-up on a fresh machine:
#   make demo   - create .venv, install flyvpr, run the main job on the built-in route
#   make test   - create .venv, install flyvpr with its test and torch extras, lint, run the tests
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip install --quiet --disable-pip-version-check

.PHONY: demo test lint bench-accuracy bench-speed clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# One stamp per install flavour; each is redone when pyproject.toml changes.
$(VENV)/.core: pyproject.toml | $(BIN)/python
	$(PIP) -e .
	touch $@

$(VENV)/.test: pyproject.toml | $(BIN)/python
	$(PIP) -e ".[test,torch,netvlad,plot]"
	touch $@ $(VENV)/.core

demo: $(VENV)/.core
	$(BIN)/flyvpr demo

lint: $(VENV)/.test
	$(BIN)/ruff check src tests benchmarks

test: lint
	$(BIN)/python -m pytest -q

bench-accuracy: $(VENV)/.test
	$(BIN)/python benchmarks/accuracy.py

bench-speed: $(VENV)/.core
	$(BIN)/python benchmarks/speed.py --json benchmarks/speed.json

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache .ruff_cache
