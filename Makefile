# Set-up in one command each, on a fresh machine (Python 3.10+ with venv):
#   make demo   creates .venv, installs torch==2.13.0 (CPU wheel) and the package, runs `torchmisspec demo`
#   make test   creates .venv, installs the package with its test extras, then runs the checks of every change
#               (about 8 minutes on 2 cores): ruff check, ruff format --check, the test suite without the tests
#               marked slow (in parallel over PYTEST_WORKERS processes), the docs build (mkdocs build --strict) and
#               the smoke reproduction of the paper's figures
#   make test-slow  the slow tier: whole loops on lab files, tutorials that fit through the ODE, study and
#               benchmark smokes (about 10 minutes); CI (.ci/run) runs make test, then make test-slow
# torch is pinned and installed with pip *before* the package, so pip never pulls a CUDA build.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH_VERSION ?= 2.13.0
# pytest workers (pytest-xdist), one torch thread each (tests/conftest.py): 8.8 -> 4.8 min on 2 cores, measured
PYTEST_WORKERS ?= 2

.PHONY: install demo test test-slow test-fast lint format docs reproduce-smoke benchmark clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install "torch==$(TORCH_VERSION)"
	$(BIN)/python -m pip install -e ".[test]"
	touch $@

install: $(VENV)/.installed

demo: install
	$(BIN)/torchmisspec demo --out demo-output

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: install
	$(BIN)/ruff format .

docs: install
	$(BIN)/mkdocs build --strict

reproduce-smoke: install
	$(BIN)/python scripts/reproduce_paper.py --all --smoke --quiet --out reproduction-output/smoke

test: lint
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS)
	$(MAKE) docs reproduce-smoke

test-slow: install
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) -m slow

test-fast: install
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS)

benchmark: install
	$(BIN)/python scripts/benchmark.py

clean:
	rm -rf $(VENV) demo-output site reproduction-output .pytest_cache
