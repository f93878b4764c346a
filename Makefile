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

# Some machines set OPENBLAS_CORETYPE and OPENBLAS_L2_SIZE to work around old OpenBLAS builds;
# on a current one they force slower kernels than it picks for the CPU itself. The benchmarks
# run without both (the tests and the demo run in the environment as it is).
BENCH_ENV := env -u OPENBLAS_CORETYPE -u OPENBLAS_L2_SIZE

bench: $(STAMP)
	$(BENCH_ENV) OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/bench_fit.py
	$(BENCH_ENV) OPENBLAS_NUM_THREADS=1 $(BIN)/python benchmarks/bench_large.py
	$(BENCH_ENV) $(BIN)/python benchmarks/bench_correct.py
	$(BENCH_ENV) $(BIN)/python benchmarks/bench_study.py

format: $(STAMP)
	$(BIN)/ruff check --fix src tests benchmarks
	$(BIN)/ruff format src tests benchmarks

clean:
	rm -rf $(VENV) out build *.egg-info src/*.egg-info
