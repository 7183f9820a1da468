# Specula: two commands work on a fresh machine with Python 3.11 and make.
#   make demo   set up .venv and run the main demo end to end
#   make test   set up .venv and run the test suite
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_STAMP := $(VENV)/.installed-demo

.PHONY: demo test test-fast lint venv bench dist clean

# Two installs in one .venv: the demo needs only the package (no test tools, no torch);
# the tests add the test extra and the optional torch/kornia extra (independent reference checks).
$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(DEMO_STAMP): pyproject.toml $(VENV)/bin/python
	$(BIN)/python -m pip install --quiet -e .
	touch $(DEMO_STAMP)

$(STAMP): pyproject.toml $(VENV)/bin/python
	$(BIN)/python -m pip install --quiet -e ".[test,torch]"
	touch $(STAMP)

venv: $(STAMP)

demo: $(DEMO_STAMP)
	$(BIN)/python -m repro.demo --out demo_output

# One BLAS thread per pytest worker: with two workers on two cores, threaded BLAS makes the
# small matrix operations of calibration 50-100x slower.
test: $(STAMP) lint
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile -q --durations=15

# The fast tier (under 3 minutes on 2 cores): every test not marked slow (tests/conftest.py, SLOW_FILES
# and @pytest.mark.slow) - the kernels, the calibration and the library without the long accuracy runs,
# sequences, the demo and the Dask cluster. `make test` runs everything.
test-fast: $(STAMP) lint
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/python -m pytest -n 2 --dist loadfile -q -m "not slow and not dask" --durations=10

# Guard rails: ruff (pyflakes, pycodestyle, import order) and the import-layer contract
# (import-linter: dic -> calibration -> kernels, no circles; pyproject.toml [tool.importlinter])
lint: $(STAMP)
	$(BIN)/ruff check kernels calibration dic bench repro tests
	$(BIN)/lint-imports

# A wheel of the three installed packages (kernels, calibration, dic) in dist/; installs with
# `pip install dist/specula_dic-*.whl` in any Python 3.11 environment (tests/dic/test_install.py).
dist: $(VENV)/bin/python
	$(BIN)/python -m pip wheel --quiet --no-deps --no-build-isolation -w dist . || $(BIN)/python -m pip wheel --quiet --no-deps -w dist .
	@ls dist/*.whl

bench: $(STAMP)
	$(BIN)/python -m bench.icgn
	$(BIN)/python -m bench.render
	$(BIN)/python -m bench.triangulate

clean:
	rm -rf $(VENV) demo_output .pytest_cache dist build
