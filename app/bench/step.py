"""Training-step benchmark: `kgs-app bench step`.

Where one training step of the whole model goes at the demo's scale (`bench raster` times the
rasteriser alone): synthesize a scene, train the fast preset past its split, then time steps
of each configuration, split into the model's evaluation (deformation field, coarse-to-fine,
K.R., covariances), render + loss, backward, and the optimisers. Configurations use the
`bench quality` short names: `full`, `kr` (no K.R.), `split` (the D3DGS-like baseline), ...
"""

from __future__ import annotations

import argparse
import os
import random
import tempfile
import time
from pathlib import Path

import torch

from .machine import machine


def time_steps(trainer, steps: int, start: int) -> dict:
    """Mean milliseconds per step of each phase of `Trainer.train_step` (batch 1), the same
    calls in the same order."""
    tr, scene = trainer, trainer.scene
    phases = dict.fromkeys(["model", "render + loss", "backward", "optimiser"], 0.0)
    for it in range(start, start + steps):
        t0 = time.perf_counter()
        tr.set_learning_rates(it)
        frame = random.choice(scene.train_frames)
        g = tr.model.at(frame.time, scene.exposure, scene.dt, noise=tr.noise.sigma(it), velocity=False)  # as loss_for
        t1 = time.perf_counter()
        del g
        loss, out = tr.loss_for(frame, it)  # evaluates the model again: subtract the first timing
        t2 = time.perf_counter()
        loss.backward()
        tr.check_gradients(it)
        t3 = time.perf_counter()
        tr.strategy.accumulate(out, frame.camera.width, frame.camera.height)
        tr.opt.step()
        tr.net_opt.step()
        tr.opt.zero_grad(set_to_none=True)
        tr.net_opt.zero_grad(set_to_none=True)
        t4 = time.perf_counter()
        phases["model"] += t1 - t0
        phases["render + loss"] += (t2 - t1) - (t1 - t0)
        phases["backward"] += t3 - t2
        phases["optimiser"] += t4 - t3
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
    ap.add_argument("--scene", default="sheet")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--blur", choices=["none", "mild", "severe"], default="mild",
                    help="exposure of the training camera (none: sharp, where K.R. needs no velocity)")
    ap.add_argument("--warmup", type=int, default=400, help="iterations trained before timing (past the split at 300)")
    ap.add_argument("--steps", type=int, default=60, help="steps timed per configuration")
    ap.add_argument("--configs", default="full,kr,split", help="short names, as in bench quality")
    ap.add_argument("--repeats", type=int, default=2, help="timing rounds, configurations interleaved")
    args = ap.parse_args(argv)
    names = select_configs(args.configs)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    root = Path(tempfile.mkdtemp(prefix="kgs-bench-step-"))
    scene = load_scene(synthesize(args.scene, root / "scene", blur=args.blur, size=args.size, frames=args.frames,
                                  progress=False))
    trainers = {}
    for name in names:
        over = config_overrides(name)
        ablate = over.pop("ablate", ())
        cfg = make_config("fast", ablate=ablate, eval_every=10**9, checkpoint_every=10**9, **over)
        tr = Trainer(scene, root / config_slug(name), cfg, progress=False)
        tr.init_model()
        for it in range(args.warmup):
            tr.train_step(it)
            tr.after_step(it)
        trainers[name] = tr
    print(f"# {args.scene} {args.size}², {args.frames} frames, {args.blur} blur, fast preset after {args.warmup} iterations; "
          f"{args.steps} steps x {args.repeats} rounds; {machine()}")
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
        print(f"| {name} | {len(m):,} | {dyn / max(len(m), 1):.0%} | {t['model']:.1f} | {t['render + loss']:.1f} | "
              f"{t['backward']:.1f} | {t['optimiser']:.1f} | **{t['step']:.1f}** |")
    return 0
