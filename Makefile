# resloc: set-up commands. `make run` and `make test` work on a fresh clone.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP_RUN := $(VENV)/.installed-run
STAMP_TEST := $(VENV)/.installed-test

.PHONY: run test lint format bench bench-quick bench-reference reproduce clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP_RUN): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[plot,fast]"
	touch $@

$(STAMP_TEST): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,all]"
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
		{ echo "installing chromium (Debian package) for the browser-viewer tests"; \
		  apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }
	touch $@ $(STAMP_RUN)

run: $(STAMP_RUN)
	$(BIN)/resloc run

# compileall: the suite starts many resloc processes (CLI runs, robots, Dask workers); where
# PYTHONDONTWRITEBYTECODE is set (as in this project's sandboxes) each would compile
# resloc's sources again (~0.25 s a process), so their bytecode is written once here.
test: $(STAMP_TEST)
	$(BIN)/ruff check src tests
	$(BIN)/ruff format --check src tests
	$(BIN)/python -m compileall -q src >/dev/null
	RESLOC_TEST_WARM_SHARES=1 $(BIN)/python -m pytest -q -n 2

lint: $(STAMP_TEST)
	$(BIN)/ruff check src tests

format: $(STAMP_TEST)
	$(BIN)/ruff format src tests
	$(BIN)/ruff check --fix src tests

# Every benchmark (resloc run's phases, every option, the scale rows) -> runs/bench/.
bench: $(STAMP_TEST)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python bench/bench_all.py

bench-quick: $(STAMP_TEST)
	OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python bench/bench_all.py --quick

# Deliberately replace the committed reference (bench/reference/) by the last runs/bench/.
bench-reference:
	$(BIN)/python bench/bench_all.py --save-reference

reproduce: $(STAMP_RUN)
	$(BIN)/resloc reproduce

clean:
	rm -rf $(VENV) runs build *.egg-info src/*.egg-info
