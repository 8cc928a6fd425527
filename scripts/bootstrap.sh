#!/usr/bin/env bash
# Creates .venv (once) with the CPU build of torch 2.13.0 installed *before* the package, so
# that pip never resolves torch from the index (which would pull GBs of CUDA wheels).
# Re-running is cheap: a stamp keyed on pyproject.toml skips the install when nothing changed.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
VENV=${KGS_VENV:-.venv}
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
stamp="$VENV/.kgs-stamp-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  "$VENV/bin/python" -m pip install -q --upgrade pip
  "$VENV/bin/python" -m pip install -q "torch==2.13.0"
  "$VENV/bin/python" -m pip install -q -e ".[dev,cluster]"  # cluster: Ray, for its tests
  rm -f "$VENV"/.kgs-stamp-*
  touch "$stamp"
fi
# The C++ rasteriser, compiled once here (cached, keyed by its sources and the compiler), so
# that no later command, and never the server, compiles it.
"$VENV/bin/kgs-app" build-ext
