"""Quality benchmark: `kgs-app bench quality`.

One synthetic scene with ground truth (sharp held-out camera, sharp training views, dynamic
masks). Every configuration is first trained for `--iterations`, all of them stepped in turn
(one step each), so that their times are measured under the same machine conditions; with
`--budget time` (the default) each one whose time differs from the first configuration's by
more than 10 % is trained again with its iteration count scaled by that measured cost ratio
(equal training time; `--budget iterations` stops after the first round). Configurations: the
full method, each ablation (`decompose` is the D3DGS-like baseline where every Gaussian deforms,
`deform` a static 3DGS), both velocity estimates and the continuous kinematic basis. Reports held-out PSNR (whole image and
inside the dynamic mask), deblur PSNR (the training views against their sharp ground truth,
also inside the dynamic mask), decomposition IoU and training time, plots held-out PSNR
against training time for all of them, and sweeps τ on the full model (re-decomposed without
retraining). Velocity EPE: the image motion the model's velocities predict (the ones the
kinematic covariance uses) against the ground-truth motion, inside the dynamic mask of the still
held-out camera, in pixels per frame interval.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import tempfile
from pathlib import Path

import torch

from .machine import machine

CONFIGS = {
    "full": {},
    "no C.F. (cf)": {"ablate": ("cf",)},
    "no K.R. (kr)": {"ablate": ("kr",)},
    "no L_reg (reg)": {"ablate": ("reg",)},
    "no L_ani (ani)": {"ablate": ("ani",)},
    "no decomposition, D3DGS-like (decompose)": {"ablate": ("decompose",)},
    "static 3DGS (deform)": {"ablate": ("deform",)},
    "velocity = paper": {"model.velocity": "paper"},
    "basis = principal": {"model.basis": "principal", "model.kr_form": "paper"},
    "kr_form = paper": {"model.kr_form": "paper"},
    "camera blur = poses": {"camera_blur": "poses"},
    "camera blur = learned": {"camera_blur": "learned"},
}


def fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


def config_key(name: str) -> str:
    """The short name `--configs` takes: the part in parentheses, else the whole name without
    spaces (`full`, `cf`, `decompose`, `velocity=paper`, ...)."""
    return name[name.index("(") + 1 : -1] if name.endswith(")") else name.replace(" ", "")


def image_cells(m: dict) -> str:
    """The four image-metric cells of a table row (held-out, its dynamic mask, deblur, its
    dynamic mask) from an `evaluate_model` dict."""
    return " | ".join(fmt(m[group][key]) for group in ("heldout", "train_view_deblur") for key in ("psnr", "psnr_dynamic"))


def mean_row(label: str, ms: list[dict]) -> str:
    """A table row of the image metrics averaged over several runs (`evaluate_model` dicts)."""

    def avg(group: str, key: str) -> float | None:
        vals = [m[group][key] for m in ms if m[group][key] is not None]
        return sum(vals) / len(vals) if vals else None

    mean = {g: {k: avg(g, k) for k in ("psnr", "psnr_dynamic")} for g in ("heldout", "train_view_deblur")}
    return f"| {label} | {image_cells(mean)} | | | | | |"


def config_label(name: str) -> str:
    """A configuration's name for a table row, its `@key=value` overrides kept: `full`,
    `no decomposition, D3DGS-like`, `no decomposition, D3DGS-like @lambda_flow=0` (rows are keyed by it, so two
    configurations must never share one)."""
    base, *sets = name.split("@")
    return " @".join([base.split(" (")[0], *sets])


def config_slug(name: str) -> str:
    """A folder name for a configuration's run (`full`, `no_decomposition_D3DGS-like`,
    `full@model.tau_1e-4`)."""
    return re.sub(r"[^A-Za-z0-9._@-]+", "_", config_label(name).replace(" @", "@"))


# Settings the bench sets for every configuration, each from its own option.
_BENCH_SET = {"seed": "--seed", "iterations": "--iterations", "eval_every": "--iterations (a tenth of them)"}


def _override(text: str, spec: str) -> tuple[str, object]:
    """`key=value` of a `--configs` entry (`parse_setting`); the settings the bench sets itself
    are refused with the option that sets them."""
    from kgs_core.train.settings import parse_setting

    try:
        key, value = parse_setting(text)
    except ValueError as exc:
        raise SystemExit(f"kgs-app bench quality: --configs: {spec!r}: {exc}") from None
    if key in _BENCH_SET:
        raise SystemExit(f"kgs-app bench quality: --configs: {spec!r}: {key} is set for every configuration by {_BENCH_SET[key]}")
    return key, value


def config_overrides(name: str) -> dict:
    """`make_config` keyword arguments of a configuration: one of CONFIGS, optionally followed
    by `@key=value` overrides (`full@noise_init_frames=0.1`, `decompose@model.tau=1e-4`): what an
    experiment varies without a new named configuration."""
    base, *sets = name.split("@")
    over = dict(CONFIGS[base])
    for text in sets:
        key, value = _override(text, name)
        over[key] = value
    return over


def select_configs(spec: str | None) -> list[str]:
    """Configuration names in CONFIGS' order (the first one sets the time budget), each entry a
    name or short name, with `@key=value` overrides kept after its base name."""
    if not spec:
        return list(CONFIGS)
    wanted = [w.strip() for w in spec.split(",") if w.strip()]
    by_key = {config_key(n): n for n in CONFIGS}
    resolved, unknown = [], []
    for w in wanted:
        base, at, sets = w.partition("@")
        name = base if base in CONFIGS else by_key.get(base)
        if name is None:
            unknown.append(w)
            continue
        full_name = name + at + sets
        config_overrides(full_name)  # a bad override fails here, before anything trains
        resolved.append(full_name)
    if unknown:
        raise SystemExit(
            f"kgs-app bench quality: --configs: unknown {', '.join(unknown)} "
            f"(choose from {', '.join(by_key)}, each optionally with @KEY=VALUE overrides)"
        )
    order = list(CONFIGS)
    return sorted(dict.fromkeys(resolved), key=lambda n: (order.index(n.split("@")[0]), "@" in n))


def parse_args(argv: list[str]) -> argparse.Namespace:
    from ..cluster import add_ray_options

    ap = argparse.ArgumentParser(prog="kgs-app bench quality", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="sheet")
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument(
        "--blur",
        default="mild",
        choices=["none", "mild", "severe"],
        help="exposure of the blurry training camera (none 0, mild 0.5, severe 1 frame)",
    )
    ap.add_argument("--seed", type=int, default=0, help="scene and training seed")
    ap.add_argument("--iterations", type=int, default=600, help="iterations of the first configuration")
    ap.add_argument(
        "--preset",
        default="fast",
        choices=["fast", "paper"],
        help="the preset every configuration starts from (paper: the paper as written, its schedule scaled to --iterations)",
    )
    ap.add_argument(
        "--budget",
        default="time",
        choices=["time", "iterations"],
        help="what every configuration gets the same of (default: training time)",
    )
    ap.add_argument(
        "--configs",
        help="comma-separated short names to run (default: all): "
        + ", ".join(config_key(n) for n in CONFIGS)
        + "; NAME@KEY=VALUE[@KEY=VALUE] overrides a training setting (full@noise_init_frames=0.1)",
    )
    ap.add_argument(
        "--cuts",
        type=int,
        default=1,
        help="with --budget time: train each re-timed configuration at this many iteration counts "
        "spread over ±5%% of the equal-time one, and report their mean too (default 1)",
    )
    ap.add_argument("--taus", default="1e-7,1e-6,1e-5,2e-5,1e-4,1e-3", help="tau sweep on the full model")
    ap.add_argument(
        "--plot",
        help="PSNR-vs-time picture (default: bench-results/quality/"
        "psnr_vs_time_SCENE_BLUR.png, one per scene and blur, so that runs of several scenes all stay)",
    )
    ap.add_argument("--out", help="keep the runs here (default: a temporary folder; with --ray on a cluster, a folder every node mounts)")
    add_ray_options(ap)
    args = ap.parse_args(argv)
    if args.plot is None:
        args.plot = f"bench-results/quality/psnr_vs_time_{args.scene}_{args.blur}.png"
    if args.cuts < 1:
        ap.error(f"--cuts must be at least 1, got {args.cuts}")
    if args.cuts > 1 and args.budget != "time":
        ap.error("--cuts applies to --budget time (it spreads the re-timed runs' iteration counts)")
    return args


def tau_sweep(run, scene, taus: list[float]) -> None:
    """Prints the full model re-decomposed at each τ from its stored K, in place as the viewer's
    live τ does (`run_view.decomposed_copy`; no retraining)."""
    from kgs_core.evaluate import evaluate_model
    from kgs_core.run_view import decomposed_copy

    print("\n## tau sweep on the full model (re-decomposed in place from the stored K, no retraining)")
    print("| tau | dynamic | held-out PSNR | in dynamic mask | decomposition IoU |")
    print("| --: | ------: | ------------: | --------------: | --------: |")
    for tau in taus:
        model = decomposed_copy(run.model, tau)
        m = evaluate_model(model, scene)
        share = float(model.dynamic.float().mean())
        print(
            f"| {tau:.0e} | {share:.1%} | {fmt(m['heldout']['psnr'])} | {fmt(m['heldout']['psnr_dynamic'])} | "
            f"{fmt(m['decomposition_iou'])} |",
            flush=True,
        )


def plot_curves(curves: dict, dashed: set, path: Path, title: str) -> None:
    """Held-out PSNR, and inside the dynamic mask, against training time for every configuration
    (`curves`: name -> [(seconds, PSNR, PSNR in mask)]; the re-timed ones `dashed`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    for col, (ax, what) in enumerate(zip(axes, ("held-out PSNR (dB)", "held-out PSNR inside the dynamic mask (dB)")), 1):
        for name, pts in curves.items():
            pts = [(p[0], p[col]) for p in pts if not math.isnan(p[col])]
            if pts:
                ax.plot(*zip(*pts), marker="o", ms=2, label=name, ls="--" if name in dashed else "-")
        ax.set_xlabel("training time (s)")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def main(argv: list[str]) -> int:
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.evaluate import evaluate_model
    from kgs_core.run import load_run, read_log
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    from ..cluster import ray_runner, timing_note
    from .equal_time import equal_time

    args = parse_args(argv)
    names = select_configs(args.configs)
    torch.set_num_threads(min(2, os.cpu_count() or 1))
    root = Path(args.out or tempfile.mkdtemp(prefix="kgs-bench-quality-"))
    folder = synthesize(
        args.scene,
        root / "scene",
        blur=args.blur,
        size=args.size,
        frames=args.frames,
        subframes=8,
        seed=args.seed,
        progress=False,
        overwrite=True,
    )
    scene = load_scene(folder)
    print(
        f"# {args.scene} {args.size}^2, {args.frames} frames, {args.blur} blur, seed {args.seed}, {args.preset} preset, "
        f"{args.iterations} iterations for {names[0]}, same {args.budget} for the others; "
        f"{machine()}"
    )
    columns = [
        "held-out PSNR",
        "in dynamic mask",
        "deblur PSNR",
        "deblur in mask",
        "decomposition IoU",
        "velocity EPE px",
        "dynamic",
        "iterations",
        "train s",
    ]
    print("| configuration | " + " | ".join(columns) + " |")
    print("| --- |" + " ---: |" * len(columns))
    curves, dashed = {}, set()

    def trainer_for(name: str, iterations: int, suffix: str = "") -> Trainer:
        over = config_overrides(name)
        ablate = over.pop("ablate", ())
        cfg = make_config(
            args.preset, ablate=ablate, iterations=iterations, eval_every=max(iterations // 10, 1), seed=args.seed, **over
        )  # a curve, not three points
        run_dir = root / (config_slug(name) + suffix)
        return Trainer(scene, run_dir, cfg, progress=False)

    def curve(run_dir: Path, seconds) -> list[tuple[float, float, float]]:
        """`(seconds, held-out PSNR, inside the dynamic mask)` per logged evaluation."""
        return [
            (seconds(r), r["psnr_heldout"], r.get("psnr_heldout_dynamic", math.nan))
            for r in read_log(run_dir)
            if not math.isnan(r["psnr_heldout"])
        ]

    def report(label: str, tr: Trainer, seconds: str) -> dict:
        run = load_run(tr.run_dir)
        m = evaluate_model(run.model, scene, static=run.static_only)
        info = tr.info
        print(
            f"| {label} | {image_cells(m)} | {fmt(m['decomposition_iou'])} | "
            f"{'n/a' if m['velocity_epe_px'] is None else format(m['velocity_epe_px'], '.3f')} | "
            f"{'static' if 'deform' in info['config']['ablate'] else format(info['dynamic_share'], '.0%')} | "
            f"{info['iteration']} | {seconds} |",
            flush=True,
        )
        return m

    # Every configuration at the same iteration count, stepped in turn, then (--budget time)
    # the ones whose cost differs re-trained at the equal-time count (`equal_time`).
    nodes: list[str] = []
    first, second = equal_time(
        names, lambda name, n, suffix: trainer_for(name, n, suffix), args.iterations, args.budget, args.cuts, **ray_runner(args, nodes)
    )
    rate = {t.name: t.seconds / t.iterations for t in first}
    for t in first:
        report(t.name, t.trainer, f"{t.seconds:.0f}")
        curves[t.name] = curve(t.trainer.run_dir, lambda r: r["train_seconds"])
    metrics: dict[str, list[dict]] = {}
    for t in second:
        label = f"{t.name}, same time" + (f" ({t.iterations} it.)" if args.cuts > 1 else "")
        metrics.setdefault(t.name, []).append(report(label, t.trainer, f"≈{t.seconds:.0f}"))
        curves[label] = curve(t.trainer.run_dir, lambda r, rate=rate[t.name]: r["iteration"] * rate)
        dashed.add(label)
    for name, ms in metrics.items():
        if len(ms) > 1:
            print(mean_row(f"{name}, same time, mean of {len(ms)} cuts", ms), flush=True)
    if nodes:
        print("\n" + timing_note(nodes, args.task_cpus))
    if "full" in names:
        tau_sweep(load_run(root / "full"), scene, [float(x) for x in args.taus.split(",")])
    if args.plot:
        plot_curves(
            curves, dashed, Path(args.plot), f"{args.scene} {args.size}², same {args.budget} ({args.iterations} iterations for {names[0]})"
        )
        print(f"\nplot: {args.plot}")
    (root / "bench.json").write_text(json.dumps({"curves": curves, "seconds_per_iteration": rate}))
    return 0
