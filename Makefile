# Quick start: `make demo` runs the worked example, `make test` runs lint and tests.
# Each target creates .venv/ with pinned dependencies (requirements-lock.txt) on first use.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench lint format clean

$(STAMP): pyproject.toml requirements-lock.txt
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q -c requirements-lock.txt -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cascal example --out out
	$(BIN)/cascal demo --out out
	$(BIN)/cascal study --trials 12000 --out out/study

test: $(STAMP)
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks
	$(BIN)/python -m pytest

bench: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/bench_fit.py
	$(BIN)/python benchmarks/bench_correct.py
	$(BIN)/python benchmarks/bench_study.py

format: $(STAMP)
	$(BIN)/ruff check --fix src tests benchmarks
	$(BIN)/ruff format src tests benchmarks

clean:
	rm -rf $(VENV) out build *.egg-info src/*.egg-info
