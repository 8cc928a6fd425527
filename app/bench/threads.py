"""Sharing the CPU: `kgs-app bench threads`.

Times a training (the demo scene, fast preset, `--iterations` steps, each in its own process as
the CLI and the server's jobs run it) alone, two at once, and beside one busy process, under
each OpenMP setting in POLICIES. The time is the run's own `train_seconds` (process start-up
and the scene's loading left out); "two at once" reports the slower of the pair, the time
until both are done. Results: docs/results.md, "Sharing the CPU".

Run it with nothing else on the machine: it measures contention on purpose, and any other load
becomes part of every number.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from .machine import machine

# Each policy is the environment a training process starts with (OpenMP reads it once, when
# torch loads libgomp). "product" is what `kgs-app train` does by itself: every core, the short
# spin, and the ThreadTuner (kgs_core/threads.py); "fixed" is the same without the tuner.
POLICIES = {
    "libgomp default": {"KGS_THREADS": "off"},
    "passive": {"KGS_THREADS": "off", "OMP_WAIT_POLICY": "PASSIVE"},
    "spin 10k (no tuner)": {"KGS_THREADS": "off", "GOMP_SPINCOUNT": "10000"},
    "product": {},
}


# What this process's own start-up put in the environment: a policy starts from none of it.
PLACEMENT_VARS = ("OMP_NUM_THREADS", "GOMP_SPINCOUNT", "OMP_WAIT_POLICY", "KGS_THREADS", "KGS_OMP_FROM_USER")


def train_once(scene: Path, out: Path, iterations: int, env: dict) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "kgs_app.cli", "train", str(scene), "--iterations", str(iterations), "--out", str(out)]
    clean = {k: v for k, v in os.environ.items() if k not in PLACEMENT_VARS}
    return subprocess.Popen(cmd, env={**clean, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def seconds(proc: subprocess.Popen, out: Path) -> float:
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"training into {out} failed: {err[-2000:]}")
    return float(json.loads((out / "run.json").read_text())["train_seconds"])


def measure(scene: Path, root: Path, iterations: int, envs: list[dict], busy: bool = False) -> float:
    """Trains one run per env at once (beside a busy process if asked); the slowest time."""
    # The busy process spins until its parent is gone, so an interrupted benchmark leaves none.
    hog = subprocess.Popen([sys.executable, "-c", f"import os\nwhile os.getppid() == {os.getpid()}: pass"]) if busy else None
    try:
        outs = [Path(tempfile.mkdtemp(dir=root)) / "run" for _ in envs]
        procs = [train_once(scene, o, iterations, e) for o, e in zip(outs, envs)]
        return max(seconds(p, o) for p, o in zip(procs, outs))
    finally:
        if hog:
            hog.kill()
            hog.wait()


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="kgs-app bench threads", description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--policies", default=",".join(POLICIES), help=f"comma-separated, of: {', '.join(POLICIES)}")
    args = ap.parse_args(argv)
    names = [p for p in args.policies.split(",") if p]
    bad = [p for p in names if p not in POLICIES]
    if bad:
        ap.error(f"unknown policy {bad[0]!r}; choose from {', '.join(POLICIES)}")

    from kgs_core.data.synth.generate import DEFAULT_SCENE, synthesize
    from kgs_core.threads import cores_available

    root = Path(tempfile.mkdtemp(prefix="kgs-bench-threads-"))
    scene = synthesize(DEFAULT_SCENE, root / "scene", blur="mild", progress=False)
    cores = cores_available()
    half = {"OMP_NUM_THREADS": str(max(1, cores // 2)), "KGS_THREADS": "off"}
    print(f"# {DEFAULT_SCENE}, fast preset, {args.iterations} iterations; {cores} cores; {machine()}")
    print("| policy | alone s | two at once s | beside a busy process s |")
    print("| --- | ---: | ---: | ---: |")
    for name in names:
        env = POLICIES[name]
        alone = measure(scene, root, args.iterations, [env])
        two = measure(scene, root, args.iterations, [env, env])
        busy = measure(scene, root, args.iterations, [env], busy=True)
        print(f"| {name} | {alone:.1f} | {two:.1f} | {busy:.1f} |", flush=True)
    two_split = measure(scene, root, args.iterations, [half, half])
    print(f"| each of the two given half the cores (OMP_NUM_THREADS={half['OMP_NUM_THREADS']}) | | {two_split:.1f} | |")
    return 0
