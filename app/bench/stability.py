"""Stability benchmark: `kgs-app bench stability`.

1. float32 against float64 on the stiff pieces of the math (kinematic basis, covariance
   refinement, exp map, SH), and the jump of Sigma_kin across the paper's reference-axis switch
   for each basis.
2. Training on stiff and extreme synthetic sequences (an impact that reverses velocity within a
   frame, blur longer than the object, 5 and 240 frames per second, 1000 frames, scene
   coordinates of order 1e5): stays finite? held-out and deblur PSNR, time. One small
   configuration for all, so the cases compare with each other, not with the demo.
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def float_errors(seed: int = 0) -> list[tuple[str, float]]:
    from kgs_core.model.kinematics import kinematic_basis, refine_covariance, so3_exp
    from kgs_core.render.covariance import quat_to_rotmat
    from kgs_core.render.sh import sh_basis

    g = torch.Generator().manual_seed(seed)
    rows = []
    d = torch.randn(4096, 3, generator=g, dtype=torch.float64)
    d /= d.norm(dim=-1, keepdim=True)
    mags = 10.0 ** torch.randint(-6, 7, (4096, 1), generator=g).double()
    v = d * mags
    for basis in ("paper", "duff", "principal"):
        q = torch.randn(4096, 4, generator=g, dtype=torch.float64)
        s = torch.exp(torch.randn(4096, 3, generator=g, dtype=torch.float64))
        M = quat_to_rotmat(q) * s[:, None, :]
        sigma = M @ M.transpose(-1, -2)
        R64 = kinematic_basis(v, basis, sigma)
        R32 = kinematic_basis(v.float(), basis, sigma.float()).double()
        rows.append((f"kinematic basis ({basis}), |v| 1e-6..1e6: max abs error", (R32 - R64).abs().max().item()))
        z = torch.zeros(4096, 3, dtype=torch.float64)
        speed = v.norm(dim=-1)
        args = (
            sigma,
            v,
            speed * 0.01,
            0.3 * torch.randn_like(z),
            0.3 * torch.randn_like(z),
            d,
            torch.tensor(-2.0, dtype=torch.float64),
            speed * 0.02,
        )
        C64 = refine_covariance(*args, basis=basis)
        C32 = refine_covariance(*[a.float() for a in args], basis=basis).double()
        rel = ((C32 - C64).norm(dim=(1, 2)) / C64.norm(dim=(1, 2))).max().item()
        rows.append((f"refined covariance ({basis}): max relative error", rel))
    from scipy.spatial.transform import Rotation

    for label, angles in (
        ("exp map, angles 1e-12..1e-3", 10.0 ** np.linspace(-12, -3, 200)),
        ("exp map, angles pi - 1e-6..pi - 1e-2", math.pi - 10.0 ** np.linspace(-6, -2, 200)),
    ):
        axes = d[:200].numpy()
        w = axes * angles[:, None]
        err = so3_exp(torch.tensor(w, dtype=torch.float32)).double().numpy() - Rotation.from_rotvec(w).as_matrix()
        rows.append((f"{label}: max abs error", float(np.abs(err).max())))
    for deg in range(4):
        err = (sh_basis(d.float(), deg).double() - sh_basis(d, deg)).abs().max().item()
        rows.append((f"SH basis degree {deg}: max abs error", err))
    return rows


def switch_jumps() -> list[tuple[str, float]]:
    import sys

    from kgs_core.model.kinematics import refine_covariance

    out = []
    for basis in ("paper", "duff", "principal"):
        worst = 0.0
        for k in range(50):
            g = torch.Generator().manual_seed(k)
            q = torch.randn(1, 4, generator=g, dtype=torch.float64)
            from kgs_core.render.covariance import quat_to_rotmat

            s = 0.01 * torch.exp(torch.rand(1, 3, generator=g, dtype=torch.float64) * math.log(20))
            M = quat_to_rotmat(q) * s[:, None, :]
            sigma = (M @ M.transpose(-1, -2)).expand(2, 3, 3)
            vs = []
            for x in (0.99 - 1e-7, 0.99 + 1e-7):
                r = math.sqrt(1 - x * x) / math.sqrt(2)
                vs.append([x, r, r])
            v = torch.tensor(vs, dtype=torch.float64)
            z = torch.zeros(2, 3, dtype=torch.float64)
            rz = torch.randn(1, 3, generator=g, dtype=torch.float64).expand(2, 3)
            C = refine_covariance(
                sigma,
                v,
                torch.full((2,), 0.05, dtype=torch.float64),
                z,
                z,
                rz,
                torch.tensor(-2.0, dtype=torch.float64),
                torch.ones(2, dtype=torch.float64),
                basis=basis,
            )
            worst = max(worst, ((C[1] - C[0]).norm() / C[0].norm()).item())
        out.append((f"jump of Sigma_kin across |u_z.e_x| = 0.99 ({basis}), step 2e-7", worst))
    del sys
    return out


def scale_coordinates(scene, factor: float, offset: float):
    """The same scene in coordinates `factor * x + offset` (cameras and points), un-normalised."""
    from dataclasses import replace

    for f in scene.frames:
        vm = f.camera.viewmat.copy()
        R, t = vm[:3, :3], vm[:3, 3]
        vm[:3, 3] = factor * t - R @ np.full(3, offset)
        f.camera = replace(f.camera, viewmat=vm)
    scene.points = factor * scene.points + offset
    return scene


CASES = {
    # name: (synth scene, blur, frames, subframes, note)
    "bounce (impact: velocity reverses within a frame)": ("bounce", "mild", 30, 4),
    "blur longer than the object (severe blur, 12 frames)": ("bounce", "severe", 12, 8),
    "5 fps (10 frames)": ("bounce", "mild", 10, 4),
    "240 fps (480 frames)": ("bounce", "mild", 480, 1),
    "1000 frames": ("bounce", "mild", 1000, 1),
    "coordinates x 1e4 + 1e5": ("bounce", "mild", 30, 4),
    "coordinates x 1e4 + 1e5, not normalised": ("bounce", "mild", 30, 4),
}


def train_case(name: str, root: Path, iterations: int, size: int, tau: float | None = None) -> dict:
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.evaluate import evaluate_model
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import NonFiniteError, train

    scene_name, blur, frames, sub = CASES[name]
    folder = root / f"scene-{abs(hash(name)) % 10**8}"
    synthesize(scene_name, folder, blur=blur, size=size, frames=frames, subframes=sub, progress=False, overwrite=True)
    if name.startswith("coordinates"):
        scene = scale_coordinates(load_scene(folder, normalize=False), 1e4, 1e5)
        scene.extras["normalized"] = False
        raw_extent = float(np.abs(np.stack([f.camera.center for f in scene.frames])).max())
        if "not normalised" not in name:
            scene.normalize()
    else:
        scene = load_scene(folder)
        raw_extent = None
    cfg = make_config(
        "fast",
        iterations=iterations,
        eval_every=max(iterations // 4, 1),
        checkpoint_every=10**9,
        decompose_at=iterations // 5,
        decompose_every=0,
        init_points=2000,
        **{
            "densify.start": iterations // 10,
            "densify.stop": int(iterations * 0.7),
            "densify.every": iterations // 10,
            "densify.opacity_reset_at": (),
            "densify.max_gaussians": 8000,
        },
        # A given τ is the threshold itself: Otsu's automatic split would otherwise place the cut.
        **({"model.tau": tau, "tau_auto": False} if tau else {}),
    )
    t0 = time.perf_counter()
    try:
        info = train(scene, root / f"run-{abs(hash(name)) % 10**8}", cfg, progress=False)
        finite = True
        error = ""
    except NonFiniteError as exc:
        info, finite, error = {}, False, str(exc)
    seconds = time.perf_counter() - t0
    row = {"case": name, "finite": finite, "seconds": seconds, "error": error, "frames": frames}
    if finite:
        from kgs_core.run import load_run

        m = evaluate_model(load_run(root / f"run-{abs(hash(name)) % 10**8}").model, scene)
        row.update(
            heldout=m.get("heldout", {}).get("psnr"),
            deblur=m.get("train_view_deblur", {}).get("psnr"),
            heldout_dynamic=m.get("heldout", {}).get("psnr_dynamic"),
            dynamic_share=info.get("dynamic_share"),
            params_finite=True,
        )
    if raw_extent is not None:
        row["raw_extent"] = raw_extent
    return row


def compare_bases(root: Path, iterations: int, size: int) -> list[dict]:
    """The same scene and budget with each kinematic basis (the switch's effect on quality)."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.evaluate import evaluate_model
    from kgs_core.run import load_run
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import train

    folder = synthesize("sheet", root / "sheet", blur="mild", size=size, frames=30, subframes=8, progress=False, overwrite=True)
    scene = load_scene(folder)
    rows = []
    for basis in ("paper", "duff", "principal"):
        # Only the paper's form of K.R. reads the basis, and K.R. must stay on for the basis to count.
        cfg = make_config("fast", iterations=iterations, kr_check_at=0.0, **{"model.basis": basis, "model.kr_form": "paper"})
        t0 = time.perf_counter()
        train(scene, root / f"basis-{basis}", cfg, progress=False)
        m = evaluate_model(load_run(root / f"basis-{basis}").model, scene)
        rows.append(
            {
                "basis": basis,
                "seconds": time.perf_counter() - t0,
                "heldout": m["heldout"]["psnr"],
                "heldout_dynamic": m["heldout"]["psnr_dynamic"],
                "deblur": m["train_view_deblur"]["psnr"],
            }
        )
    return rows


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="kgs-app bench stability", description=__doc__.split("\n\n")[0])
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--skip-training", action="store_true")
    ap.add_argument(
        "--tau",
        type=float,
        help="override the decomposition threshold (a low one makes most Gaussians dynamic, so the kinematic path runs everywhere)",
    )
    ap.add_argument("--cases", help="comma-separated case numbers (1-based) to train")
    ap.add_argument(
        "--compare-basis",
        type=int,
        metavar="ITERATIONS",
        help="also train the sheet scene with each kinematic basis for this many iterations",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    print("## float32 against float64")
    for label, v in float_errors() + switch_jumps():
        print(f"| {label} | {v:.2e} |")
    if args.compare_basis:
        root = Path(tempfile.mkdtemp(prefix="kgs-bench-basis-"))
        print(f"\n## kinematic basis, sheet {args.size * 2}^2, 30 frames, fast preset, {args.compare_basis} iterations")
        print("| basis | held-out PSNR | held-out PSNR (dynamic mask) | deblur PSNR | seconds |")
        print("| ----- | ------------: | ---------------------------: | ----------: | ------: |")
        for r in compare_bases(root, args.compare_basis, args.size * 2):
            print(
                f"| {r['basis']} | {r['heldout']:.2f} | {r['heldout_dynamic']:.2f} | {r['deblur']:.2f} | {r['seconds']:.0f} |", flush=True
            )
    if args.skip_training:
        return 0
    names = list(CASES)
    if args.cases:
        names = [names[int(i) - 1] for i in args.cases.split(",")]
    print(
        f"\n## training on stiff and extreme sequences ({args.size}^2, {args.iterations} iterations, fast preset"
        + (f", tau {args.tau:g}" if args.tau else "")
        + ")"
    )
    print("| case | frames | finite | held-out PSNR | in dynamic mask | deblur PSNR | dynamic | seconds |")
    print("| ---- | -----: | ------ | ------------: | --------------: | ----------: | ------: | ------: |")
    root = Path(tempfile.mkdtemp(prefix="kgs-bench-stability-"))
    for name in names:
        r = train_case(name, root, args.iterations, args.size, args.tau)
        fmt = lambda x: "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2f}"  # noqa: E731
        dyn = "n/a" if r.get("dynamic_share") is None else f"{r['dynamic_share']:.0%}"
        print(
            f"| {name} | {r['frames']} | {'yes' if r['finite'] else 'NO: ' + r['error']} | {fmt(r.get('heldout'))} | "
            f"{fmt(r.get('heldout_dynamic'))} | {fmt(r.get('deblur'))} | {dyn} | {r['seconds']:.0f} |",
            flush=True,
        )
    return 0
