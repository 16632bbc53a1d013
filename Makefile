# Set-up in one command each, on a fresh machine (Python 3.10+ with venv):
#   make demo   creates .venv, installs torch==2.13.0 (CPU wheel) and the package, runs `torchmisspec demo`
#   make test   creates .venv, installs the package with its test extras, runs the test suite
# torch is pinned and installed with pip *before* the package, so pip never pulls a CUDA build.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
TORCH_VERSION ?= 2.13.0

.PHONY: install demo test test-all benchmark lint clean

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

test: install
	$(BIN)/python -m pytest -q

test-all: install
	$(BIN)/python -m pytest -q -m "slow or not slow"

benchmark: install
	$(BIN)/python scripts/benchmark.py

lint: install
	$(BIN)/python -m pip install ruff
	$(BIN)/ruff check torchmisspec tests scripts

clean:
	rm -rf $(VENV) demo-output .pytest_cache
