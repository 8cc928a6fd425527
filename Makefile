# Two entry points; both set up .venv on first use (see scripts/bootstrap.sh).
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test lint wheel-check bench setup

setup:
	@bash scripts/bootstrap.sh

demo: setup
	$(VENV)/bin/kgs-app demo

test: setup
	@if command -v node >/dev/null; then node --test frontend/tests/; else echo "node not found: JS unit tests skipped"; fi
	$(PY) -m pytest -q tests

# Style, import order and formatting (ruff), and types of the modules listed in pyproject.toml's
# [tool.mypy]; run by .ci/run. `ruff format .` fixes what the format check finds.
lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/mypy

# The built wheel, installed into a fresh venv, trains the demo and serves the viewer.
wheel-check: setup
	PYTHON=$(PY) bash scripts/check_wheel.sh

bench: setup
	$(VENV)/bin/kgs-app bench raster
