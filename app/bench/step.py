"""Training-step benchmark: `kgs-app bench step`.

Where one training step of the whole model goes (`bench raster` times the rasteriser alone):
synthesize a scene (or read a scene folder, e.g. an ingest at full size, with the preset fitted
to it), train the fast preset past its decomposition, then time steps of each configuration, split into
the model's evaluation (deformation field, coarse-to-fine, K.R., covariances), render + loss,
backward, and the optimisers; `--profile` adds the operations that take the time (torch's
profiler, self time). Configurations use the `bench quality` short names: `full`, `kr` (no
K.R.), `decompose` (the D3DGS-like baseline), ...
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import torch

from .machine import machine


def time_steps(trainer, steps: int, start: int) -> dict:
    """Mean milliseconds per step of each phase of the real `Trainer.train_step`: the model's
    evaluation (`KinematicsGS.at`, timed by wrapping it), render + loss (the rest of the
    forward), backward, and the optimisers. `after_step` runs between steps, as in training,
    untimed."""
    tr = trainer
    phases = dict.fromkeys(["model", "render + loss", "backward", "optimiser"], 0.0)
    model_seconds = [0.0]
    at = tr.model.at

    def timed_at(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return at(*args, **kwargs)
        finally:
            model_seconds[0] += time.perf_counter() - t0

    last = [0.0]

    def on_phase(name: str) -> None:
        now = time.perf_counter()
        phases["render + loss" if name == "forward" else name] += now - last[0]
        last[0] = now

    tr.model.at, tr.on_phase = timed_at, on_phase
    try:
        for it in range(start, start + steps):
            last[0] = time.perf_counter()
            tr.train_step(it)
            tr.after_step(it)
    finally:
        del tr.model.at
        tr.on_phase = None
    phases["render + loss"] -= model_seconds[0]
    phases["model"] = model_seconds[0]
    out = {k: 1000 * v / steps for k, v in phases.items()}
    out["step"] = sum(out.values())
    return out


def main(argv: list[str]) -> int:
    from kgs_app.bench.quality import config_overrides, config_slug, select_configs
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    ap = argparse.ArgumentParser(prog="kgs-app bench step", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="sheet", help="a synthetic scene's name, or a scene folder")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument(
        "--blur",
        choices=["none", "mild", "severe"],
        default="mild",
        help="exposure of the training camera (none: sharp, where K.R. needs no velocity)",
    )
    ap.add_argument("--warmup", type=int, default=400, help="iterations trained before timing (past the decomposition at 300)")
    ap.add_argument("--steps", type=int, default=60, help="steps timed per configuration")
    ap.add_argument("--configs", default="full,kr,decompose", help="short names, as in bench quality")
    ap.add_argument("--repeats", type=int, default=2, help="timing rounds, configurations interleaved")
    ap.add_argument(
        "--decompose-at",
        type=int,
        help="the decomposition's iteration (default: the preset's; set it below "
        "--warmup to time a large scene after its decomposition without training to it)",
    )
    ap.add_argument("--profile", action="store_true", help="also list the operations of the first configuration's steps by self time")
    ap.add_argument(
        "--levels",
        help="comma-separated image divisors, e.g. 1,2,4: also time the first configuration's "
        "step at each resolution level (as the training's downscales draws them)",
    )
    args = ap.parse_args(argv)
    names = select_configs(args.configs)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    root = Path(tempfile.mkdtemp(prefix="kgs-bench-step-"))
    folder = Path(args.scene)
    if folder.is_dir():
        scene = load_scene(folder)
    else:
        scene = load_scene(synthesize(args.scene, root / "scene", blur=args.blur, size=args.size, frames=args.frames, progress=False))
    trainers = {}
    for name in names:
        over = config_overrides(name)
        ablate = over.pop("ablate", ())
        if args.decompose_at is not None:
            over["decompose_at"] = args.decompose_at
        cfg = make_config("fast", ablate=ablate, scene=scene if folder.is_dir() else None, eval_every=10**9, checkpoint_every=10**9, **over)
        tr = Trainer(scene, root / config_slug(name), cfg, progress=False)
        tr.init_model()
        for it in range(args.warmup):
            tr.train_step(it)
            tr.after_step(it)
        trainers[name] = tr
    cam = scene.train_frames[0].camera
    what = (
        f"{folder.name} {cam.width}x{cam.height}, {len(scene.train_frames)} training frames"
        if folder.is_dir()
        else f"{args.scene} {args.size}², {args.frames} frames, {args.blur} blur"
    )
    print(f"# {what}, fast preset after {args.warmup} iterations; {args.steps} steps x {args.repeats} rounds; {machine()}")
    print("| configuration | Gaussians | dynamic | model ms | render + loss ms | backward ms | optimiser ms | step ms |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    best: dict[str, dict] = {}
    for r in range(args.repeats):  # interleaved so that the machine's drift hits every configuration
        for name, tr in trainers.items():
            t = time_steps(tr, args.steps, args.warmup + r * args.steps)
            if name not in best or t["step"] < best[name]["step"]:
                best[name] = t
    for name, tr in trainers.items():
        t, m = best[name], tr.model
        dyn = int(m.dynamic.sum()) if m.decomposed else len(m)
        print(
            f"| {name} | {len(m):,} | {dyn / max(len(m), 1):.0%} | {t['model']:.1f} | {t['render + loss']:.1f} | "
            f"{t['backward']:.1f} | {t['optimiser']:.1f} | **{t['step']:.1f}** |"
        )
    if args.levels:
        name, tr = next(iter(trainers.items()))
        divisors = [int(k) for k in args.levels.split(",")]
        times = time_levels(tr, divisors, args.steps, args.warmup + args.repeats * args.steps)
        cam = tr.scene.train_frames[0].camera
        print(f"\n{name}: a step at each resolution level, best of two interleaved rounds")
        print("| level | ms a step | against the first |\n| --- | ---: | ---: |")
        for k in divisors:
            print(f"| 1/{k} ({cam.width // k}x{cam.height // k}) | {times[k]:.1f} | {times[k] / times[divisors[0]]:.2f} |")
    if args.profile:
        name, tr = next(iter(trainers.items()))
        print(f"\n{name}: operations by self time over {args.steps} steps (ms a step)")
        print(profile_table(tr, args.steps, args.warmup + args.repeats * args.steps))
    return 0


def time_levels(trainer, divisors: list[int], steps: int, start: int) -> dict[int, float]:
    """Milliseconds a step at each image divisor k (the training's own coarse-to-fine levels,
    train/image_levels.py: intrinsics scaled, images and flows area-averaged), interleaved
    twice, the best kept."""
    best, it = {}, start
    try:
        for _ in range(2):
            for k in divisors:
                trainer.divisor_override = k
                t0 = time.perf_counter()
                for _ in range(steps):
                    trainer.train_step(it)
                    it += 1
                ms = 1000 * (time.perf_counter() - t0) / steps
                best[k] = min(best.get(k, ms), ms)
    finally:
        trainer.divisor_override = None
    return best


def profile_table(trainer, steps: int, start: int, rows: int = 20) -> str:
    """The operations of `steps` training steps by self CPU time, as a markdown table."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for it in range(start, start + steps):
            trainer.train_step(it)
            trainer.after_step(it)
    events = sorted(prof.key_averages(), key=lambda e: e.self_cpu_time_total, reverse=True)
    total = sum(e.self_cpu_time_total for e in events)
    lines = ["| operation | calls a step | self ms a step | share |", "| --- | ---: | ---: | ---: |"]
    for e in events[:rows]:
        lines.append(
            f"| {e.key} | {e.count / steps:.1f} | {e.self_cpu_time_total / 1000 / steps:.1f} | "
            f"{e.self_cpu_time_total / max(total, 1):.1%} |"
        )
    return "\n".join(lines)
