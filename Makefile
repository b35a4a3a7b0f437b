# Two entry points do all the set-up on a fresh machine:
#   make demo   - create .venv, install flyvpr, run the main job on the built-in route
#   make test   - create .venv, install flyvpr with its test and torch extras, lint, build the docs,
#                 check the results pages, run the tests
# Also: make docs (the documentation site, warnings are errors), make results (re-render the
# results pages and the README's table from the benchmarks' JSON).
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
PIP := $(BIN)/python -m pip install --quiet --disable-pip-version-check

.PHONY: demo test lint docs results bench-accuracy bench-speed clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

# One stamp per install flavour; each is redone when pyproject.toml changes.
$(VENV)/.core: pyproject.toml | $(BIN)/python
	$(PIP) -e .
	touch $@

$(VENV)/.test: pyproject.toml | $(BIN)/python
	$(PIP) -e ".[test,torch,netvlad,plot,docs,recordings,dask,view]"
	touch $@ $(VENV)/.core $(VENV)/.docs $(VENV)/.lint

# Lint needs ruff and mypy alone (no torch: mypy skips the optional extras, see pyproject.toml).
$(VENV)/.lint: pyproject.toml | $(BIN)/python
	$(PIP) -e ".[lint]"
	touch $@ $(VENV)/.core

$(VENV)/.docs: pyproject.toml | $(BIN)/python
	$(PIP) -e ".[docs]"
	touch $@ $(VENV)/.core

demo: $(VENV)/.core
	$(BIN)/flyvpr demo

lint: $(VENV)/.lint
	$(BIN)/ruff check src tests benchmarks docs
	$(BIN)/ruff format --check src tests benchmarks docs
	$(BIN)/mypy

test: $(VENV)/.test lint docs
	$(BIN)/python -m pytest -q

# -E: read every page afresh, so a warning in an unchanged page still fails the build.
docs: $(VENV)/.docs
	$(BIN)/sphinx-build -b html -E -W --keep-going -n -q docs docs/_build/html
	@echo "docs: docs/_build/html/index.html"

results: $(VENV)/.core
	$(BIN)/python docs/generate_results.py

bench-accuracy: $(VENV)/.test
	$(BIN)/python benchmarks/accuracy.py

bench-speed: $(VENV)/.core
	$(BIN)/python benchmarks/speed.py --json benchmarks/speed.json

clean:
	rm -rf $(VENV) build src/*.egg-info .pytest_cache .ruff_cache .mypy_cache docs/_build docs/api
