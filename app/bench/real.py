"""Real-footage benchmark: `kgs-app bench real [CLIP ...]`.

Each clip is a synchronised pair: a blurry hand-held video (training) and a sharp camera beside
it (held out), as in BARD-GS; by default the shared `walk` and `kitchen` pairs. Each pair is
ingested once (cached under `--out`), then the full method, the D3DGS-like baseline (`decompose`)
and a static 3DGS (`deform`) are trained at equal wall time (`equal_time`, as `bench quality`)
and evaluated on every sharp-camera frame:

* PSNR and SSIM on the full frame;
* the same inside the dynamic-region mask, which needs no ground truth: the pixels where the
  static 3DGS of the first round (same iterations as the full method) errs by more than 0.15,
  as regions, dilated (`kgs_core.evaluate.static_error_mask`). It is computed once per clip and
  is the same for every configuration;
* how much of the sharp frames' fine detail the renders hold, over the whole frame (`detail`)
  and inside the mask (`detail_mask`), each beside the blurry input's share (the training frame
  nearest in time): a soft render scores well below 1 however well it is placed, and a
  reconstruction that deblurs scores above its input;
* beside them, the mask PSNR with every held-out frame rendered up to a frame earlier or later
  (`best_time_offset`): how far the model's moving parts are from the sharp camera's along
  their motion;
* side-by-side pictures (blurry input | full method | D3DGS-like | sharp frame, mask outlined),
  the same columns as crops at full size where the sharp frame holds the most detail outside the
  mask (`crops_<clip>.png`: text, edges), and held-out PSNR against training time.

Everything lands in `--out` (a markdown table `results.md`, `views_<clip>.png`,
`crops_<clip>.png`, `psnr_vs_time_<clip>.png`); copy what should stay into docs/.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np
import torch

from .machine import machine

DEFAULT_CLIPS = ("walk", "kitchen")
DEFAULT_DATA = "../shared/data/bardgs"


def resolve_clip(spec: str, data: Path) -> tuple[str, Path, Path]:
    """`walk` (looked up as `DATA/walk_blur.mp4` + `DATA/walk_sharp.mp4`) or a path to a
    `NAME_blur.EXT` video whose `NAME_sharp.EXT` lies beside it -> (name, blurry, sharp)."""
    p = Path(spec)
    if p.suffix:
        blur = p
        if not blur.stem.endswith("_blur"):
            raise SystemExit(f"kgs-app bench real: {spec}: a clip path must be NAME_blur.EXT with NAME_sharp.EXT beside it")
        name = blur.stem[: -len("_blur")]
        sharp = blur.with_name(f"{name}_sharp{blur.suffix}")
    else:
        name, blur, sharp = spec, data / f"{spec}_blur.mp4", data / f"{spec}_sharp.mp4"
    for v in (blur, sharp):
        if not v.is_file():
            raise SystemExit(f"kgs-app bench real: clip {spec!r}: {v} not found (--data names the folder of the pairs)")
    return name, blur, sharp


def ingest_cached(name: str, blur: Path, sharp: Path, size: int, root: Path) -> Path:
    """The clip's scene folder, ingested on first use and reused afterwards (keyed by the
    clip's name and size only: delete `--out/scenes/NAME SIZE` after changing a video)."""
    from kgs_core.data.ingest import ingest

    out = root / "scenes" / f"{name}{size}"
    if not (out / "dataset.json").is_file():
        rep = ingest(blur, out, eval_video=sharp, max_size=size, overwrite=True)
        print(
            f"# ingested {name}: {rep.registered}/{rep.frames} + {rep.eval_registered}/{rep.eval_frames} frames, "
            f"{rep.mean_reprojection_error_px:.2f} px, {sum(rep.seconds.values()):.0f} s",
            flush=True,
        )
    return out


@torch.no_grad()
def sharp_camera_metrics(model, scene, static: bool, masks: list[np.ndarray]) -> dict:
    """PSNR/SSIM over every held-out (sharp camera) frame, whole and inside `masks` (one per
    frame; frames whose mask is empty are left out of the masked means), and the renders' fine
    detail as a share of the sharp frames' over the frame (`detail`) and inside the masks
    (`detail_mask`), each beside the blurry input's (`evaluate.DetailShare`; 1 is as detailed
    as the sharp camera)."""
    from kgs_core.evaluate import DetailShare, masked_ssim, nearest_input, render_at
    from kgs_core.losses import psnr, ssim

    ps, ss, mps, mss = [], [], [], []
    detail = DetailShare()
    for f, mask in zip(scene.test_frames, masks):
        gt = torch.from_numpy(f.image())
        img = render_at(model, f, 0.0, scene.dt, static=static)[0].image.clamp(0, 1)
        ps.append(psnr(img, gt))
        ss.append(float(ssim(img, gt)))
        detail.add(img.numpy(), nearest_input(scene, f), gt.numpy(), mask)
        if mask.any():
            mps.append(psnr(img, gt, torch.from_numpy(mask)))
            s = masked_ssim(img, gt, mask)
            if s is not None:
                mss.append(s)
    mean = lambda v: float(np.mean(v)) if v else math.nan  # noqa: E731
    nan = lambda v: math.nan if v is None else v  # noqa: E731
    d = detail.result()
    return {
        "psnr": mean(ps),
        "ssim": mean(ss),
        "psnr_mask": mean(mps),
        "ssim_mask": mean(mss),
        "detail": nan(d["detail"]),
        "detail_input": nan(d["detail_input"]),
        "detail_mask": nan(d["detail_dynamic"]),
        "detail_input_mask": nan(d["detail_input_dynamic"]),
    }


CROP_PX = 160  # side of the full-size crops (crops_<clip>.png)

# Frame intervals by which `best_time_offset` shifts the held-out renders in time.
TIME_OFFSETS = (-1.0, -0.5, 0.5, 1.0)


@torch.no_grad()
def best_time_offset(model, scene, masks: list[np.ndarray], at_zero: float, offsets=TIME_OFFSETS) -> dict:
    """Where the model's moving parts best meet the held-out camera's: every held-out frame
    rendered at its time + each of `offsets` frame intervals (clamped to the clip), scored
    inside `masks`. Returns the offset (0 included, whose mask PSNR is `at_zero`) with the
    highest mean mask PSNR, and that PSNR. A diagnostic beside the scored numbers, which stay at
    each frame's own time: the two cameras' videos are synchronised only to about a frame, so
    their moving content can be that far apart (docs/real-footage.md, "What limits the moving
    person")."""
    from kgs_core.evaluate import render_at
    from kgs_core.losses import psnr

    best = (at_zero, 0.0)
    for d in offsets:
        vals = []
        for f, mask in zip(scene.test_frames, masks):
            if mask.any():
                shifted = dataclasses.replace(f, time=min(max(f.time + d * scene.dt, 0.0), 1.0))
                img = render_at(model, shifted, 0.0, scene.dt)[0].image.clamp(0, 1)
                vals.append(psnr(img, torch.from_numpy(f.image()), torch.from_numpy(mask)))
        if vals and float(np.mean(vals)) > best[0]:
            best = (float(np.mean(vals)), d)
    return {"psnr_mask_best_offset": best[0], "best_offset_frames": best[1]}


@torch.no_grad()
def dynamic_masks(static_model, scene) -> list[np.ndarray]:
    from kgs_core.evaluate import render_at, static_error_mask

    return [
        static_error_mask(render_at(static_model, f, 0.0, scene.dt, static=True)[0].image.numpy(), f.image()) for f in scene.test_frames
    ]


@torch.no_grad()
def side_by_side(runs: list, scene, masks: list[np.ndarray], path: Path, count: int = 4, crop: int = 0) -> None:
    """Rows at `count` times: blurry input | each run at the sharp camera | sharp frame (the
    dynamic-region mask outlined in red on it). `crop` > 0: each cell is the `crop`² window at
    full size where the sharp frame holds the most detail outside the mask (`detail_crop`),
    unscaled, so that sharpness shows."""
    from PIL import Image
    from scipy import ndimage

    from kgs_core.evaluate import detail_crop, nearest_input, render_at
    from kgs_core.io import atomic_write_bytes

    test = scene.test_frames
    rows = []
    for k in np.linspace(0, len(test) - 1, count + 2).round().astype(int)[1:-1]:
        f = test[k]
        gt = f.image().copy()
        cells = [nearest_input(scene, f)] + [
            render_at(r.model, f, 0.0, scene.dt, static=r.static_only)[0].image.clamp(0, 1).numpy() for r in runs
        ]
        h = min(c.shape[0] for c in cells + [gt])
        w = min(c.shape[1] for c in cells + [gt])
        if crop:
            size = min(crop, h, w)
            y, x = detail_crop(gt[:h, :w], size, exclude=masks[k][:h, :w])
            window = (slice(y, y + size), slice(x, x + size))
        else:
            edge = masks[k] & ~ndimage.binary_erosion(masks[k], iterations=1)
            gt[edge] = (1.0, 0.1, 0.1)
            window = (slice(0, h), slice(0, w))
        rows.append(np.concatenate([c[:h, :w][window] for c in cells + [gt]], 1))
    import io

    buf = io.BytesIO()
    Image.fromarray((np.concatenate(rows, 0) * 255).round().astype(np.uint8)).save(buf, format="png")
    atomic_write_bytes(path, buf.getvalue())


def plot_curves(curves: dict, title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.8), dpi=110)
    for label, pts in curves.items():
        if pts:
            ax.plot(*zip(*pts), marker="o", ms=2, label=label, ls="--" if "same time" in label else "-")
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("sharp-camera PSNR, 4 frames (dB)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def share(value: float) -> str:
    """A detail share, or n/a where it was not computed (the input's in the mask, when the two
    cameras' frames differ in size)."""
    return "n/a" if math.isnan(value) else f"{value:.2f}"


def table_row(label: str, seed: str, r: dict) -> str:
    dyn = "static" if r["dynamic_share"] is None else f"{r['dynamic_share']:.0%}"
    return (
        f"| {label} | {seed} | {r['psnr']:.2f} | {r['ssim']:.3f} | {r['psnr_mask']:.2f} | {r['ssim_mask']:.3f} | "
        f"{share(r['detail'])} ({share(r['detail_input'])}) | {share(r['detail_mask'])} ({share(r['detail_input_mask'])}) | "
        f"{r['psnr_mask_best_offset']:.2f} ({r['best_offset_frames']:+.2g}) | "
        f"{dyn} | {r['gaussians']:,.0f} | {r['iterations']:.0f} | {r['seconds']:.0f} |"
    )


def mean_over_seeds(by_seed: dict[int, dict]) -> dict:
    """One configuration's results: its only seed's, or the mean over its seeds with each
    seed's under `seeds`."""
    if len(by_seed) == 1:
        return next(iter(by_seed.values()))
    rows = list(by_seed.values())
    mean = {k: (None if rows[0][k] is None else float(np.mean([r[k] for r in rows]))) for k in rows[0] if k != "run"}
    return {**mean, "seeds": {str(seed): r for seed, r in by_seed.items()}}


def fill_equal_time(per_seed: dict[str, dict[int, dict]]) -> None:
    """A configuration re-timed ("X, same time") for some seeds only: where a seed's own run of
    X already took the budget's time it was not re-trained, and that run is its equal-time
    result. Filled in, so that the mean over seeds covers every seed."""
    for label in [lb for lb in per_seed if lb.endswith(", same time")]:
        for seed, r in per_seed.get(label[: -len(", same time")], {}).items():
            per_seed[label].setdefault(seed, r)


def main(argv: list[str]) -> int:
    from kgs_core.data.formats import load_scene
    from kgs_core.run import load_run, read_log
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    from ..cluster import add_ray_options, ray_runner, timing_note
    from .equal_time import equal_time
    from .quality import config_label, config_overrides, config_slug, select_configs

    ap = argparse.ArgumentParser(prog="kgs-app bench real", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "clips",
        nargs="*",
        default=list(DEFAULT_CLIPS),
        help="clip names in --data (default: walk kitchen) or paths to NAME_blur.EXT videos",
    )
    ap.add_argument(
        "--data",
        default=os.environ.get("KGS_BARDGS", DEFAULT_DATA),
        help=f"folder of NAME_blur.mp4 / NAME_sharp.mp4 pairs (default ${{KGS_BARDGS}} or {DEFAULT_DATA})",
    )
    ap.add_argument("--size", type=int, default=320, help="longest image side for ingest (default 320)")
    ap.add_argument("--preset", default="fast", choices=["fast", "paper"])
    ap.add_argument("--iterations", type=int, help="iterations of the first configuration (default: the preset's, fitted to the clip)")
    ap.add_argument(
        "--configs",
        default="full,decompose,deform",
        help="configurations as for bench quality; 'deform' (the static 3DGS) is always trained: it defines the dynamic-region mask",
    )
    ap.add_argument("--budget", default="time", choices=["time", "iterations"])
    ap.add_argument("--cuts", type=int, default=1)
    ap.add_argument(
        "--seeds",
        default="0",
        help="comma-separated training seeds. With more than one, every configuration is trained with "
        "each (runs under OUT/runs/CLIP/sSEED), the mask comes from the first seed's static 3DGS, "
        "and the table gives each seed's row and their mean (one seed's mask PSNR is noisy: "
        "docs/results.md)",
    )
    ap.add_argument(
        "--out",
        default="bench-results/real",
        help="runs, cached scenes and results (default %(default)s; with --ray on a cluster, a folder every node mounts)",
    )
    add_ray_options(ap)
    args = ap.parse_args(argv)
    if args.cuts < 1 or (args.cuts > 1 and args.budget != "time"):
        ap.error("--cuts is at least 1, and more than 1 only with --budget time")
    if args.size < 32 or (args.iterations is not None and args.iterations < 1):
        ap.error(f"--size must be at least 32 and --iterations at least 1 (got {args.size}, {args.iterations})")
    try:
        seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--seeds takes comma-separated whole numbers, got {args.seeds!r}")
    if not seeds or len(set(seeds)) != len(seeds):
        ap.error(f"--seeds needs at least one seed and no repeats, got {args.seeds!r}")
    if len(seeds) > 1 and args.cuts > 1:
        ap.error("--cuts above 1 takes one seed (each cut's iteration count differs from seed to seed)")
    names = select_configs(args.configs)
    static_name = select_configs("deform")[0]
    if static_name not in names:
        names.append(static_name)
    clips = [resolve_clip(c, Path(args.data)) for c in args.clips]  # every clip checked before any work
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    root = Path(args.out)
    root.mkdir(parents=True, exist_ok=True)
    lines = [
        f"# bench real: {args.preset} preset, {args.size} px, same {args.budget}, "
        f"seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}; {machine()}",
        "",
    ]
    summary = {}
    for name, blur, sharp in clips:
        scene_dir = ingest_cached(name, blur, sharp, args.size, root)
        scene = load_scene(scene_dir)

        # Every configuration trains the full method's plan: at full size a time budget's
        # (its iterations and Gaussian budget, train/fitting.py), else the fitted iterations.
        # Given, so that no run revises it (train/budget.py): each configuration gets the same.
        planned = make_config(args.preset, scene=scene)
        iterations = args.iterations or planned.iterations
        plan = {"densify.max_gaussians": planned.densify.max_gaussians} if not args.iterations and planned.time_budget else {}
        print(
            f"# {name}: {len(scene.train_frames)} training + {len(scene.test_frames)} sharp frames at "
            f"{scene.frames[0].camera.width}x{scene.frames[0].camera.height}; {iterations} iterations for "
            f"{names[0]}",
            flush=True,
        )
        masks, rows, per_seed = None, [], {}
        for seed in seeds:
            runs = root / "runs" / name / (f"s{seed}" if len(seeds) > 1 else "")

            def trainer_for(config: str, iterations: int, suffix: str, scene=scene, runs=runs, seed=seed, plan=plan) -> Trainer:
                over = {**plan, **config_overrides(config), "iterations": iterations}
                ablate = over.pop("ablate", ())
                cfg = make_config(args.preset, ablate=ablate, seed=seed, scene=scene, **over)
                cfg.eval_every = max(cfg.iterations // 10, 1)
                return Trainer(scene, runs / (config_slug(config) + suffix), cfg, progress=False)

            nodes: list[str] = []
            first, second = equal_time(names, trainer_for, iterations, args.budget, args.cuts, **ray_runner(args, nodes))
            if masks is None:  # one mask for every configuration and seed: the first seed's static 3DGS
                static_run = load_run(next(t for t in first if t.name == static_name).trainer.run_dir)
                masks = dynamic_masks(static_run.model, scene)
                share = float(np.mean([m.mean() for m in masks]))
                lines += [
                    f"## {name}",
                    "",
                    f"{len(scene.train_frames)} + {len(scene.test_frames)} frames at "
                    f"{scene.frames[0].camera.width}x{scene.frames[0].camera.height}; dynamic-region mask: "
                    f"{share:.1%} of the sharp-camera pixels." + (f" {timing_note(nodes, args.task_cpus)}." if nodes else ""),
                    "",
                    "| configuration | seed | PSNR | SSIM | PSNR in mask | SSIM in mask | detail (input) | detail in mask "
                    "(input) | in mask at the best time offset (frames) | dynamic | Gaussians | iterations | "
                    "train s |",
                    "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
                ]
                print("\n".join(lines[-5:]), flush=True)
            curves, shown = {}, []
            for t in first + second:
                run = load_run(t.trainer.run_dir)
                m = sharp_camera_metrics(run.model, scene, run.static_only, masks)
                m.update(
                    {"psnr_mask_best_offset": m["psnr_mask"], "best_offset_frames": 0.0}
                    if run.static_only
                    else best_time_offset(run.model, scene, masks, m["psnr_mask"])
                )
                label = config_label(t.name) + (", same time" if t.retimed else "")
                label += f" ({t.iterations} it.)" if t.retimed and args.cuts > 1 else ""
                info = t.trainer.info
                result = {
                    **m,
                    "iterations": t.iterations,
                    "seconds": t.seconds,
                    "gaussians": info["gaussians"],
                    "dynamic_share": None if run.static_only else info["dynamic_share"],
                    "run": str(t.trainer.run_dir),
                }
                per_seed.setdefault(label, {})[seed] = result
                rows.append(table_row(label, str(seed), result))
                print(rows[-1], flush=True)
                rate = t.seconds / t.iterations
                curves[label] = [
                    (r["iteration"] * rate, r["psnr_heldout"]) for r in read_log(t.trainer.run_dir) if not math.isnan(r["psnr_heldout"])
                ]
                # The pictures show each configuration at the shared budget: the re-timed run where there is one.
                if t.name != static_name and (t.retimed or not any(s.name == t.name for s in second)):
                    shown.append((label, run))
            if seed == seeds[0]:  # pictures and curves of the first seed
                pictures = root / f"views_{name}.png"
                side_by_side([r for _, r in shown], scene, masks, pictures)
                side_by_side([r for _, r in shown], scene, masks, root / f"crops_{name}.png", count=2, crop=CROP_PX)
                plot_curves(
                    curves, f"{name}: held-out (sharp camera) PSNR, same {args.budget}, seed {seed}", root / f"psnr_vs_time_{name}.png"
                )
        fill_equal_time(per_seed)
        results = {label: mean_over_seeds(by_seed) for label, by_seed in per_seed.items()}
        if len(seeds) > 1:
            rows += [table_row(f"**{label}**", "mean", r) for label, r in results.items()]
        lines += rows
        lines += [
            "",
            f"Pictures ({pictures.name}; crops_{name}.png at full size, {CROP_PX} px windows where the sharp "
            f"frame has the most detail outside the mask; seed {seeds[0]}), columns: blurry input | "
            + " | ".join(lb for lb, _ in shown)
            + " | sharp frame (mask outlined). Detail: the render's fine detail "
            "as a share of the sharp frame's, the blurry input's in brackets.",
            "",
        ]
        summary[name] = results
    (root / "results.md").write_text("\n".join(lines) + "\n")
    (root / "results.json").write_text(json.dumps(summary, indent=1))
    print(f"\nresults: {root / 'results.md'}")
    return 0
