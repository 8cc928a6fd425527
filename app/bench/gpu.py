"""The CUDA rasteriser against the CPU one: `kgs-app bench gpu [--device cuda] [--gaussians N]`.

Renders the same Gaussians (a random scene, or a trained run's model at mid-clip with `--run`)
with gsplat on the GPU and with the C++ CPU rasteriser, and prints the mean absolute difference
in 8-bit levels (the GPU issue's bar: at most 1) and each one's frames per second at 960×540.
Needs CUDA and gsplat (`kinematics-gs[cuda]`); says so and exits 2 without them.
"""

from __future__ import annotations

import argparse
import json
import time

import torch

from kgs_core.device import DeviceError, resolve_device
from kgs_core.render import packed_covariance, rasterize
from kgs_core.render.gsplat_backend import GsplatUnavailable, load_gsplat
from kgs_core.render.random_scene import random_scene

from .machine import machine


def frames_per_second(draw, wait, seconds: float = 2.0) -> float:
    draw()
    wait()
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        draw()
        n += 1
    wait()
    return n / (time.perf_counter() - t0)


def gaussians_to_compare(args) -> dict:
    """`{means, covars (N, 6), opacities, colors, viewmat, K, width, height}` on the CPU."""
    if args.run:
        from kgs_core.data.formats import load_scene
        from kgs_core.model.render import camera_tensors
        from kgs_core.render.sh import eval_sh
        from kgs_core.run import load_run

        run = load_run(args.run)
        scene = load_scene(run.scene_path())
        frames = scene.test_frames or scene.train_frames
        frame = frames[len(frames) // 2]
        viewmat, K = camera_tensors(frame.camera)
        with torch.no_grad():
            g = run.model.at(frame.time)
            colors = eval_sh(g.sh, g.means, -viewmat[:3, :3].T @ viewmat[:3, 3], run.model.config.sh_degree)
        size = dict(width=frame.camera.width, height=frame.camera.height)
        return dict(means=g.means, covars=g.covars6, opacities=g.opacities, colors=colors, viewmat=viewmat, K=K, **size)
    sc = random_scene(args.gaussians, width=960, height=540, overlap=args.overlap, seed=0)
    cov6 = packed_covariance(sc.quats, sc.scales, backend="torch")
    return dict(means=sc.means, covars=cov6, opacities=sc.opacities, colors=sc.colors, viewmat=sc.viewmat, K=sc.K, width=960, height=540)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="kgs-app bench gpu", description=__doc__)
    ap.add_argument("--device", default="cuda", help="the GPU to compare on (cuda or cuda:N)")
    ap.add_argument("--gaussians", type=int, default=200_000, help="random scene size (without --run)")
    ap.add_argument("--overlap", type=float, default=30.0, help="random scene: Gaussians per pixel")
    ap.add_argument("--run", help="compare on this run's model at mid-clip instead of a random scene")
    ap.add_argument("--json", help="also write the numbers here")
    args = ap.parse_args(argv)
    try:
        device = resolve_device(args.device)
        if device.type != "cuda":
            raise DeviceError(f"--device {args.device}: the comparison needs a CUDA device")
        load_gsplat()
    except (DeviceError, GsplatUnavailable) as exc:
        print(f"kgs-app bench gpu: {exc}")
        return 2
    s = gaussians_to_compare(args)
    cam = dict(width=s["width"], height=s["height"])

    def render(backend: str, on: torch.device):
        t = {k: v.to(on) for k, v in s.items() if isinstance(v, torch.Tensor)}
        return rasterize(t["means"], t["opacities"], t["viewmat"], t["K"], covars=t["covars"], colors=t["colors"], backend=backend, **cam)

    with torch.no_grad():
        cpu = render("cpu", torch.device("cpu")).image.clamp(0, 1)
        gpu = render("gsplat", device).image.clamp(0, 1).cpu()
        diff = float((cpu - gpu).abs().mean() * 255)
        fps_gpu = frames_per_second(lambda: render("gsplat", device), torch.cuda.synchronize)
        fps_cpu = frames_per_second(lambda: render("cpu", torch.device("cpu")), lambda: None, seconds=5.0)
    out = {
        "gaussians": len(s["means"]),
        "size": f"{s['width']}x{s['height']}",
        "mean_abs_diff_255": round(diff, 3),
        "fps_gsplat": round(fps_gpu, 1),
        "fps_cpu": round(fps_cpu, 2),
        "gpu": torch.cuda.get_device_name(device),
        "machine": machine(),
    }
    print(json.dumps(out, indent=1))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0
