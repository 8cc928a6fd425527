# Two entry points; both set up .venv on first use (see scripts/bootstrap.sh).
VENV ?= .venv
PY := $(VENV)/bin/python

.PHONY: demo test bench setup

setup:
	@bash scripts/bootstrap.sh

demo: setup
	$(VENV)/bin/kgs-app demo

test: setup
	@if command -v node >/dev/null; then node --test frontend/tests/; else echo "node not found: JS unit tests skipped"; fi
	$(PY) -m pytest -q tests

bench: setup
	$(VENV)/bin/kgs-app bench raster
