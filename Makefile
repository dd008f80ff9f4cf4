# torchfilt developer entry points. `make demo` and `make test` are the README's quick start.
#
# The CPU build of torch is installed first and pinned, so that the unpinned `torch>=2.1` in
# pyproject.toml is already satisfied and pip never fetches a multi-GB CUDA build. On a machine
# where torch==2.13.0 is not on disk, point pip at the CPU wheels:
#   make test PIP_TORCH_ARGS="--index-url https://download.pytorch.org/whl/cpu"
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_SPEC ?= torch==2.13.0
PIP_TORCH_ARGS ?=
OUT ?= out

.PHONY: setup demo test test-slow test-all lint docs bench gpu-check reproduce plaza clean

setup: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q $(PIP_TORCH_ARGS) "$(TORCH_SPEC)"
	$(BIN)/python -m pip install -q -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python scripts/quickstart.py --out $(OUT)/quickstart

# -n auto: one pytest worker per core (xdist), whole test files per worker (loadfile) so that
# a module's fixtures are built once; conftest.py gives every worker one torch thread.
test: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile

test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m slow

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -n auto --dist loadfile -m "slow or not slow"

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# the documentation site (mkdocs.yml), strict: a warning, broken link or unresolved reference fails
docs: $(STAMP)
	$(BIN)/mkdocs build --strict --site-dir site

bench: $(STAMP)
	$(BIN)/python scripts/bench_filter.py --cckf --out $(OUT)/bench_filter

# Every CUDA test and GPU figure in one run (scripts/gpu_check.py, whose docstring gives the
# one-call command for the lent, offline GPU machine); GPU_CHECK_ARGS=--dry-run on a CPU.
gpu-check: $(STAMP)
	$(BIN)/python scripts/gpu_check.py --out $(OUT)/gpu_check $(GPU_CHECK_ARGS)

reproduce: $(STAMP)
	$(BIN)/python scripts/reproduce_reentry.py --out $(OUT)/reentry
	$(BIN)/python scripts/reproduce_cckf.py --out $(OUT)/cckf --mfckf-dir $(OUT)/reentry
	$(BIN)/python scripts/reproduce_dmc.py --out $(OUT)/dmc
	$(BIN)/python scripts/reproduce_dmc.py --double-layer --out $(OUT)/dmc-double-layer

plaza: $(STAMP)
	$(BIN)/python scripts/plaza_example.py --out $(OUT)/plaza

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .ruff_cache .mypy_cache .hypothesis
