# Two entry points (README): `make demo` and `make test`. Everything else is optional.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
# The package with the test extras (make test, lint, bench), and the package alone (make demo:
# the test extras bring MAVProxy, and with it OpenCV and VTK, about 1.2 GB the demo never uses).
STAMP := $(VENV)/.installed
DEMO_STAMP := $(VENV)/.installed-package
# The matrices here are small: threaded BLAS only contends with pytest for the 2 cores.
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1

.PHONY: demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e '.[test]'
	touch $(STAMP) $(DEMO_STAMP)

# pip's own lines are the progress of the minute or two a first install takes.
$(DEMO_STAMP): pyproject.toml
	@echo "installing ins-health and what the demo needs into $(VENV) (a minute or two, once)"
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --disable-pip-version-check --progress-bar off -e .
	touch $(DEMO_STAMP)

demo: $(DEMO_STAMP)
	$(BIN)/ins-health demo

test: $(STAMP)
	$(BIN)/python -m pytest -q -n 2

# ruff (rules and their exceptions in pyproject.toml), the formatter's check, and mypy
# (strict on estimators/ and protocols/, default on service/: pyproject.toml).
lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

bench: $(STAMP)
	for b in benchmarks/bench_*.py; do echo "== $$b"; $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
