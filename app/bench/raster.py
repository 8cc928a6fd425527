"""Rasteriser benchmark: forward/backward ms per backend and a full training step.

Run as `kgs-app bench raster`. Numbers are medians over repeats; all configurations run in
one process, one after the other, so they compare side by side on the same machine state.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass

import torch

from kgs_core.losses import photometric_loss
from kgs_core.render import rasterize
from kgs_core.render.random_scene import random_scene
from kgs_core.render.sh import rgb_to_sh0

from .machine import machine

# The torch reference materialises (pixels x Gaussians) per tile row: only small sizes fit.
TORCH_MAX_WORK = 10_000 * 128 * 128


@dataclass
class Row:
    backend: str
    n: int
    res: int
    forward_ms: float
    backward_ms: float
    list_len: float  # mean Gaussians listed per 16x16 tile
    overlap: float  # mean Gaussians reaching alpha >= 1/255 at a pixel (ignoring early stop)


def _timed(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def bench_raster(backend: str, n: int, res: int, repeat: int) -> Row:
    scene = random_scene(n, res, res, overlap=30.0, seed=0)
    params = [t.clone().requires_grad_(True) for t in scene.tensors()]
    means, quats, scales, opac, colors = params
    grad = torch.rand(res, res, 3, generator=torch.Generator().manual_seed(1))

    def forward():
        return rasterize(means, opac, scene.viewmat, scene.K, res, res, quats=quats, scales=scales, colors=colors, backend=backend)

    out = forward()
    (out.image * grad).sum().backward()  # warm-up (and extension build)
    fwd, bwd = [], []
    for _ in range(repeat):
        for p in params:
            p.grad = None
        t0 = time.perf_counter()
        out = forward()
        t1 = time.perf_counter()
        (out.image * grad).sum().backward()
        t2 = time.perf_counter()
        fwd.append((t1 - t0) * 1e3)
        bwd.append((t2 - t1) * 1e3)
    box = out.info.get("tile_offsets")
    list_len = float(box[-1]) / (box.numel() - 1) if box is not None else float("nan")
    return Row(backend, n, res, statistics.median(fwd), statistics.median(bwd), list_len, overlap(out, opac))


def overlap(out, opacities) -> float:
    """Mean number of Gaussians whose alpha >= 1/255 ellipse covers a pixel: the ellipse
    area is pi * 2 ln(255 o) * sqrt(det cov2d), with det cov2d = 1 / det(conic)."""
    with torch.no_grad():
        vis = out.radii > 0
        a, b, c = out.conics[vis].double().unbind(-1)
        level = 2 * torch.log(255 * opacities.detach()[vis].double())
        area = math.pi * level / torch.sqrt(a * c - b * b)
        return float(area.sum()) / (out.image.shape[0] * out.image.shape[1])


# The C++ stages of one cpu forward + backward, in call order: extension function -> label.
STAGES = {
    "covar_forward": "covariance forward",
    "project_forward": "projection forward",
    "bin_gaussians": "binning",
    "raster_forward": "raster forward",
    "raster_backward": "raster backward",
    "project_backward": "projection backward",
    "covar_backward": "covariance backward",
}


class _TimedExtension:
    """Stands in for the loaded extension and adds each call's wall time to `spent[name]`."""

    def __init__(self, ext, spent: dict[str, float]):
        self._ext, self._spent = ext, spent

    def __getattr__(self, name):
        fn = getattr(self._ext, name)

        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self._spent[name] = self._spent.get(name, 0.0) + (time.perf_counter() - t0) * 1e3

        return timed


def stage_times(n: int, res: int, repeat: int) -> dict:
    """Mean ms per call of each C++ stage (`STAGES`) inside real cpu `rasterize` forward +
    backward calls on the benchmark's scene, the mean fwd+bwd, and the rest: what autograd
    and Python add. The stages are timed inside the same calls as the total, so the rest is
    not confounded by the VM's drift between separate measurements (which once made it look
    twice its size); a stage called alone in a loop runs 3-5 % faster on warm caches."""
    from kgs_core.render import _ext

    ext = _ext.load()
    scene = random_scene(n, res, res, overlap=30.0, seed=0)
    params = [t.clone().requires_grad_(True) for t in scene.tensors()]
    means, quats, scales, opac, colors = params
    grad = torch.rand(res, res, 3, generator=torch.Generator().manual_seed(1))

    def forward_backward():
        for p in params:
            p.grad = None
        out = rasterize(means, opac, scene.viewmat, scene.K, res, res, quats=quats, scales=scales, colors=colors, backend="cpu")
        (out.image * grad).sum().backward()

    forward_backward()  # warm-up: the reusable buffers grow to size once
    spent: dict[str, float] = {}
    load = _ext.load
    _ext.load = lambda verbose=False: _TimedExtension(ext, spent)
    try:
        total = sum(_timed(forward_backward, repeat)) / repeat
    finally:
        _ext.load = load
    ms = {label: spent.get(name, 0.0) / repeat for name, label in STAGES.items()}
    return {"n": n, "res": res, "ms": ms, "fwd_bwd_ms": total, "rest_ms": total - sum(ms.values())}


def bench_train_step(n: int, res: int, repeat: int, sh_degree: int = 3) -> dict:
    """One optimisation step: SH colours, projection, raster, L1 + D-SSIM, backward, Adam."""
    scene = random_scene(n, res, res, overlap=30.0, seed=0)
    target = rasterize(
        scene.means, scene.opacities, scene.viewmat, scene.K, res, res, quats=scene.quats, scales=scene.scales, colors=scene.colors
    ).image.detach()
    g = torch.Generator().manual_seed(2)
    means = (scene.means + 0.01 * torch.randn(scene.means.shape, generator=g)).requires_grad_(True)
    quats = scene.quats.clone().requires_grad_(True)
    log_scales = scene.scales.log().requires_grad_(True)
    opac_logits = torch.logit(scene.opacities.clamp(1e-4, 1 - 1e-4)).requires_grad_(True)
    sh = torch.zeros(n, (sh_degree + 1) ** 2, 3)
    sh[:, 0] = rgb_to_sh0(torch.rand(n, 3, generator=g))
    sh.requires_grad_(True)
    opt = torch.optim.Adam([means, quats, log_scales, opac_logits, sh], lr=1e-3, fused=True)

    def step():
        opt.zero_grad(set_to_none=True)
        out = rasterize(
            means,
            torch.sigmoid(opac_logits),
            scene.viewmat,
            scene.K,
            res,
            res,
            quats=quats,
            scales=log_scales.exp(),
            sh_coeffs=sh,
            sh_degree=sh_degree,
        )
        loss = photometric_loss(out.image, target)
        loss.backward()
        opt.step()

    step()
    times = _timed(step, repeat)
    return {"n": n, "res": res, "sh_degree": sh_degree, "step_ms": statistics.median(times)}


def peak_memory_mb(n: int, res: int) -> float:
    """Peak resident memory added by one forward + backward, in a fresh process: the kernel's
    high-water mark (VmHWM) is reset after warm-up through /proc/self/clear_refs."""
    code = f"""
import re, torch
from kgs_app.bench.raster import bench_raster
from kgs_core.render import _ext
_ext.load()
bench_raster('cpu', 2000, 64, 1)
def status(key):
    return int(re.search(key + r":\\s+(\\d+)", open('/proc/self/status').read()).group(1))
base = status('VmRSS')
open('/proc/self/clear_refs', 'w').write('5')
bench_raster('cpu', {n}, {res}, 1)
print((status('VmHWM') - base) / 1024)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if out.returncode != 0:
        raise RuntimeError(f"memory probe failed: {out.stderr.strip()[-500:]}")
    return float(out.stdout.strip().splitlines()[-1])


def stages_markdown(stages: list[dict]) -> list[str]:
    """One column per measured size: each stage's ms inside the pipeline, the rest, the total."""
    sizes = " | ".join(f"N = {st['n']:,} at {st['res']}²" for st in stages)
    lines = [f"| stage (ms, inside rasterize's fwd+bwd) | {sizes} |", "|---|" + "---:|" * len(stages)]
    for label in STAGES.values():
        lines.append(f"| {label} | " + " | ".join(f"{st['ms'][label]:.2f}" for st in stages) + " |")
    lines.append("| autograd + Python (the rest) | " + " | ".join(f"{st['rest_ms']:.2f}" for st in stages) + " |")
    lines.append("| fwd+bwd | " + " | ".join(f"{st['fwd_bwd_ms']:.2f}" for st in stages) + " |")
    return lines


def to_markdown(rows: list[Row], step: dict, mem: dict | None, stages: list[dict] | None = None) -> str:
    lines = [
        f"Machine: {machine()}",
        "",
        "| backend | N | image | forward ms | backward ms | fwd+bwd ms | Gaussians per tile list | Gaussians per pixel |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.backend} | {r.n:,} | {r.res}² | {r.forward_ms:.1f} | {r.backward_ms:.1f} | "
            f"{r.forward_ms + r.backward_ms:.1f} | {'—' if math.isnan(r.list_len) else format(r.list_len, '.0f')} | {r.overlap:.0f} |"
        )
    lines += [
        "",
        f"Full training step (SH degree {step['sh_degree']}, projection, raster, L1 + D-SSIM, "
        f"backward, Adam), N = {step['n']:,} at {step['res']}²: **{step['step_ms']:.1f} ms**",
    ]
    if mem:
        lines.append(f"Peak extra resident memory, one forward + backward, N = {mem['n']:,} at {mem['res']}²: **{mem['mb']:.0f} MB**")
    if stages:
        lines += ["", *stages_markdown(stages)]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="kgs-app bench raster", description=__doc__)
    ap.add_argument("--n", type=int, nargs="+", default=[10_000, 50_000, 200_000])
    ap.add_argument("--res", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--backends", nargs="+", default=["cpu", "torch"], choices=["cpu", "torch"])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocess")
    ap.add_argument(
        "--stages",
        action="store_true",
        help="also time each C++ stage inside the cpu forward + backward, per N and size, and what autograd and Python add",
    )
    ap.add_argument("--markdown", help="also write the results as markdown to this file")
    ap.add_argument("--json", help="also write raw results as JSON to this file")
    args = ap.parse_args(argv)

    rows: list[Row] = []
    for n in args.n:
        for res in args.res:
            for backend in args.backends:
                if backend == "torch" and n * res * res > TORCH_MAX_WORK:
                    continue
                row = bench_raster(backend, n, res, args.repeat if backend == "cpu" else 1)
                rows.append(row)
                print(
                    f"{backend:5s} N={n:>7,} {res:>4}²  fwd {row.forward_ms:8.1f} ms  bwd {row.backward_ms:8.1f} ms"
                    f"  list {row.list_len:6.0f}  overlap {row.overlap:5.1f}",
                    flush=True,
                )
    step = bench_train_step(50_000, 256, args.repeat)
    print(f"train step N=50,000 256²: {step['step_ms']:.1f} ms", flush=True)
    mem = None
    if not args.no_memory:
        mem = {"n": max(args.n), "res": max(args.res), "mb": peak_memory_mb(max(args.n), max(args.res))}
        print(f"peak extra memory N={mem['n']:,} {mem['res']}²: {mem['mb']:.0f} MB")
    stages = []
    if args.stages:
        for n in args.n:
            for res in args.res:
                st = stage_times(n, res, max(args.repeat, 5))
                stages.append(st)
                print(
                    f"stages N={n:>7,} {res:>4}²  "
                    + "  ".join(f"{k} {v:.2f}" for k, v in st["ms"].items())
                    + f"  rest {st['rest_ms']:.2f}  fwd+bwd {st['fwd_bwd_ms']:.2f}",
                    flush=True,
                )
    md = to_markdown(rows, step, mem, stages)
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write(md + "\n")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(
                {"machine": machine(), "rows": [asdict(r) for r in rows], "train_step": step, "memory": mem, "stages": stages}, f, indent=2
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
