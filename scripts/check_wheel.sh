#!/usr/bin/env bash
# Builds the wheel, installs it into a fresh virtual environment (torch 2.13.0 CPU first, so
# that pip never resolves a CUDA build) and checks that the installed package, away from the
# source tree, trains the demo scene and serves the viewer. Run by .ci/run after the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
work=$(mktemp -d)
trap 'kill "${server:-}" 2>/dev/null || true; rm -rf "$work"' EXIT
"$PY" -m pip wheel -q --no-deps -w "$work/dist" .
"$PY" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "torch==2.13.0"
"$work/venv/bin/python" -m pip install -q "$work"/dist/kinematics_gs-*.whl
cd "$work"  # nothing of the source tree on the path from here on
"$work/venv/bin/kgs-app" build-ext  # the set-up step: the server refuses to start without it
"$work/venv/bin/kgs-app" demo --workspace "$work/ws" --iterations 40 --no-serve
port=$(( 20000 + RANDOM % 20000 ))
"$work/venv/bin/kgs-app" serve --workspace "$work/ws" --port "$port" > "$work/serve.log" 2>&1 &
server=$!
"$work/venv/bin/python" - "$port" <<'PY' || { echo "wheel check: the viewer was not served"; cat "$work/serve.log"; exit 1; }
import sys, time, urllib.request
base = f"http://127.0.0.1:{sys.argv[1]}"
for _ in range(120):  # the server imports torch and builds nothing: a few seconds
    try:
        index = urllib.request.urlopen(base + "/", timeout=5).read().decode()
        break
    except OSError:
        time.sleep(0.5)
else:
    sys.exit("no answer from kgs-app serve")
assert "<html" in index.lower(), "/ is not the viewer's page"
for path in ("/js/main.js", "/css/style.css", "/shaders/splat.frag.glsl", "/api/runs"):
    urllib.request.urlopen(base + path, timeout=10).read()
PY
echo "wheel check: the installed wheel trained the demo and served the viewer"
