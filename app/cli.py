"""`kgs-app`: the command line of Kinematics-GS. Every command listed here works."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .cli_args import add_options, options_from, positive_int


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job: synthesize the built-in scene, train the fast preset, evaluate it, serve the viewer."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import DEFAULT_SCENE, synthesize
    from kgs_core.evaluate import evaluate_run
    from kgs_core.threads import tuner_for_process
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import train

    work = Path(args.workspace)
    scene_dir, run_dir = work / "scenes" / DEFAULT_SCENE, work / "runs" / f"{DEFAULT_SCENE}-fast"
    if not (scene_dir / "dataset.json").is_file():
        print(f"[1/4] synthesizing the built-in scene '{DEFAULT_SCENE}' -> {scene_dir}")
        synthesize(DEFAULT_SCENE, scene_dir, blur="mild", overwrite=True)
    else:
        print(f"[1/4] scene already there: {scene_dir}")
    scene = load_scene(scene_dir)
    done = (run_dir / "model.pt").is_file() and not args.retrain
    if done:
        print(f"[2/4] run already trained: {run_dir} (--retrain to train again)")
    else:
        print(f"[2/4] training the fast preset -> {run_dir}")
        import shutil

        shutil.rmtree(run_dir, ignore_errors=True)
        over = {"iterations": args.iterations} if args.iterations else {}
        train(scene, run_dir, make_config("fast", scene=scene, **over), threads=tuner_for_process())
    print("[3/4] evaluating")
    evaluate_run(run_dir)
    print((run_dir / "metrics.md").read_text())
    print(f"PSNR against training time: {run_dir / 'psnr_vs_time.png'}")
    if args.no_serve:
        return 0
    print("[4/4] serving the viewer (Ctrl-C to stop)")
    from kgs_backend.main import serve
    from kgs_backend.settings import Settings

    serve(Settings(workspace=work, port=args.port))
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    """Render a named synthetic scene with ground truth to a dataset folder."""
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.job_options import SynthOptions

    o = options_from(args, SynthOptions)
    out = synthesize(out=args.out, overwrite=args.overwrite, **o.model_dump())  # the options are its arguments
    print(f"wrote {out} (Nerfies + D-NeRF layouts, ground truth under sharp/, mask/, motion/)")
    return 0


def cmd_ingest(args: argparse.Namespace) -> int:
    """Video -> frames -> sharpness -> pycolmap SfM -> Nerfies-layout scene."""
    from kgs_core.data.ingest import ingest
    from kgs_core.job_options import IngestOptions

    o = options_from(args, IngestOptions)
    rep = ingest(
        args.video,
        args.out,
        eval_video=args.eval_video,
        cache_dir=False if args.no_cache else True,
        overwrite=args.overwrite,
        **o.ingest_arguments(),
    )
    print(
        f"{rep.mapper} mapper: posed {rep.registered}/{rep.frames} training frames"
        + (f", {rep.eval_registered}/{rep.eval_frames} frames of the second camera" if rep.eval_video else "")
        + f"; mean reprojection error {rep.mean_reprojection_error_px:.2f} px; {rep.points} points"
    )
    if rep.lens:
        lens = rep.lens
        print(
            f"lens: {lens['model']} refit "
            + (
                f"kept, reprojection error {lens['before_px']:.2f} -> {lens['after_px']:.2f} px"
                if lens["kept"]
                else f"not kept ({lens.get('reason', '')})"
            )
        )
    for a in rep.attempts:
        print(f"  tried {a['mapper']}: {a['outcome']}, {a['registered_fraction']:.0%} posed in {a['seconds']:.1f} s")
    reuse = (
        f"; poses reused from the cache ({rep.poses_from}; --mapper NAME maps anew)"
        if rep.poses_from
        else "; decoded frames, features and matches reused from the cache"
        if rep.cached
        else ""
    )
    print(f"held out: {rep.holdout}; stride {rep.stride} ({rep.stride_reason})" + reuse)
    print(f"seconds {rep.seconds} -> {args.out}")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    """Train Kinematics-GS on a scene folder; writes a run directory."""
    from kgs_core.data.formats import load_scene
    from kgs_core.job_options import TrainOptions
    from kgs_core.threads import tuner_for_process
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import train

    o = options_from(args, TrainOptions)
    overrides, ablate = o.overrides(), tuple(o.ablate)
    make_config(o.preset, ablate=ablate, **overrides)  # a bad option fails before the scene is read
    scene = load_scene(args.scene)
    cfg = make_config(o.preset, ablate=ablate, scene=scene, **overrides)
    if args.init_from:
        from dataclasses import replace

        cfg = replace(cfg, init_from=str(Path(args.init_from).resolve()))
    for key, why in cfg.fitted.items():
        print(f"fitted to the scene: {key} = {why}")
    out = Path(args.out)
    if out.exists() and any(out.iterdir()) and not args.resume:
        raise FileExistsError(f"{out} exists: pass --resume to continue it, or choose another --out")
    info = train(scene, out, cfg, resume=args.resume, threads=tuner_for_process())
    print(
        f"{info['status']}: {info['iteration']} iterations in {info['train_seconds']:.0f} s, "
        f"{info['gaussians']:,} Gaussians ({info['dynamic_share']:.0%} dynamic), held-out PSNR "
        f"{info['final_psnr_heldout']:.2f} dB -> {out}"
    )
    return 0


def cmd_train_many(args: argparse.Namespace) -> int:
    """Trains every scene x preset x configuration x seed into OUT/runs/, in turn here or as Ray
    tasks (--ray); a table and OUT/train-many.json summarise them."""
    import json

    from kgs_core.data.formats import load_scene
    from kgs_core.io import atomic_write_text
    from kgs_core.threads import tuner_for_process
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import Trainer

    from .bench.quality import config_overrides, config_slug, select_configs
    from .cluster import run_trainers

    configs = select_configs(args.configs)
    presets = [p for p in args.presets.split(",") if p]
    seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    if args.task_cpus < 1:
        raise ValueError(f"--task-cpus must be at least 1, got {args.task_cpus}")
    for p in presets:
        make_config(p)  # an unknown preset fails before any scene is read
    out = Path(args.out)
    trainers = []
    for folder in args.scenes:
        scene = load_scene(folder)  # every scene checked before any training
        name = Path(folder).resolve().name
        for preset in presets:
            for config in configs:
                for seed in seeds:
                    run_dir = out / "runs" / f"{name}-{preset}-{config_slug(config)}-s{seed}"
                    if run_dir.exists() and any(run_dir.iterdir()):
                        raise FileExistsError(f"{run_dir} exists: remove it or choose another --out")
                    over = config_overrides(config) | ({"iterations": args.iterations} if args.iterations else {})
                    ablate = over.pop("ablate", ())
                    cfg = make_config(preset, ablate=ablate, scene=scene, seed=seed, **over)
                    trainers.append(Trainer(scene, run_dir, cfg, progress=args.ray is None))
    print(
        f"{len(trainers)} trainings: {len(args.scenes)} scenes x {len(presets)} presets x {len(configs)} "
        f"configurations x {len(seeds)} seeds -> {out / 'runs'}"
    )
    if args.ray is None:
        nodes = []
        for i, t in enumerate(trainers, 1):
            print(f"[{i}/{len(trainers)}] {t.run_dir.name}")
            t.threads = tuner_for_process()
            t.run()
    else:
        nodes = run_trainers(trainers, args.ray, args.task_cpus)
    rows = [
        {
            "run": str(t.run_dir),
            "iterations": t.info["iteration"],
            "train_seconds": round(t.train_seconds, 1),
            "psnr_heldout": t.info.get("final_psnr_heldout"),
            "gaussians": t.info["gaussians"],
            "dynamic_share": t.info["dynamic_share"],
            **({"node": n} if n else {}),
        }
        for t, n in zip(trainers, nodes or [None] * len(trainers))
    ]
    atomic_write_text(out / "train-many.json", json.dumps(rows, indent=1))
    print("| run | iterations | train s | held-out PSNR | Gaussians | dynamic |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        psnr = "n/a" if r["psnr_heldout"] is None else f"{r['psnr_heldout']:.2f}"
        print(
            f"| {Path(r['run']).name} | {r['iterations']} | {r['train_seconds']:.0f} | {psnr} | "
            f"{r['gaussians']:,} | {r['dynamic_share']:.0%} |"
        )
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    """Metrics of a run against its scene's sharp ground truth (metrics.json and .md)."""
    from kgs_core.evaluate import evaluate_run

    evaluate_run(args.run, args.scene, device=args.device)
    print((Path(args.run) / "metrics.md").read_text())
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    """Per-frame .ply / .splat, a .splatv, an mp4 or a .glb of ellipsoids from a run."""
    from kgs_core.export import export_run
    from kgs_core.job_options import ExportOptions

    o = options_from(args, ExportOptions)
    res = export_run(args.run, out=args.out, overwrite=args.force, keyframes=args.keyframes, **o.export_arguments())
    rep = res.report
    print(f"wrote {res.path} ({len(res.files)} file{'s' if len(res.files) != 1 else ''}, {rep['gaussians']:,} Gaussians, LoD {rep['lod']})")
    if "note" in rep:
        print(rep["note"])
    if "fit" in rep:
        f = rep["fit"]
        print(
            f"splatv motion fit over {f['dynamic']:,} dynamic Gaussians: position RMS {f['position_rms']:.2e} "
            f"({f['position_rms_rel']:.2%} of the scene extent), max {f['position_max']:.2e}; covariance "
            f"relative error mean {f['covariance_rel_mean']:.3f}, max {f['covariance_rel_max']:.3f}"
        )
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    """Serve a workspace (runs, renders, splat streams) and the browser viewer."""
    import secrets

    from kgs_backend.main import serve
    from kgs_backend.settings import Settings

    settings = Settings(
        workspace=Path(args.workspace),
        host=args.host,
        port=args.port,
        token=args.token,
        cors_origins=args.cors or [],
        allowed_hosts=args.allow_host or [],
        max_upload_mb=args.max_upload_mb,
        register=[Path(p) for p in args.paths],
    )
    if not settings.loopback and not settings.token:
        settings.token = secrets.token_urlsafe(24)
        print(f"binding {args.host} (not loopback): access token required, generated: {settings.token}")
    if args.demo:
        from kgs_backend.registry import Workspace
        from kgs_backend.routers.system import start_demo

        ws = Workspace(settings.workspace)
        if not ws.list("runs"):
            print("empty workspace: synthesizing the demo scene and training the fast preset (watch it in the browser)")
            settings.start_demo = lambda app: start_demo(app.state.ws, app.state.jobs)
    serve(settings)
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    """The desktop viewer: a run directory in process, or a run on a running `kgs-app serve`."""
    if args.server:
        if not args.run_id:
            raise ValueError("--server needs --run-id (the run's id on that server)")
        from kgs_app.viewer.source import RemoteSource

        source = RemoteSource(args.server, args.run_id, args.token)
    else:
        if not args.run:
            raise ValueError("give a run directory, or --server URL --run-id ID")
        from kgs_app.viewer.source import LocalSource

        source = LocalSource(args.run)
    from kgs_app.viewer.model import ViewerModel

    model = ViewerModel(source)
    model.state.t = args.time
    if args.frame is not None:
        if not 0 <= args.frame < len(source.frames):
            raise ValueError(f"--frame must be in 0..{len(source.frames) - 1}")
        model.use_frame_camera(args.frame)
    if args.offscreen:
        if not args.screenshot:
            raise ValueError("--offscreen renders one image: pass --screenshot PATH")
        from kgs_app.viewer.gl_renderer import render_offscreen
        from kgs_app.viewer.window import save_png

        model.sync()
        s = model.state
        img = render_offscreen(
            model.static, model.dynamic, s.viewmat, s.K, model.width, model.height, show=s.show_mask, overlay=args.overlay
        )
        print(f"screenshot: {save_png(args.screenshot, img)}")
        return 0
    from kgs_app.viewer.window import run_window

    model.state.overlay = args.overlay
    run_window(model, max_frames=args.frames, screenshot=args.screenshot)
    return 0


def cmd_build_ext(args: argparse.Namespace) -> int:
    """Compile (or find cached) the C++ rasteriser and print where it lives."""
    from kgs_core.render import _ext

    t0 = time.perf_counter()
    try:
        mod = _ext.load(verbose=args.verbose)
    except _ext.ExtensionUnavailable as exc:
        print(f"C++ rasteriser unavailable: {exc}", file=sys.stderr)
        return 1
    print(f"C++ rasteriser ready in {time.perf_counter() - t0:.1f} s ({mod.simd_path()} SIMD path): {mod.__file__}")
    return 0


BENCHMARKS = ("raster", "step", "quality", "real", "ingest", "stability", "serve", "threads", "open", "gpu")  # modules of kgs_app.bench


def cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    return importlib.import_module(f"kgs_app.bench.{args.what}").main(args.rest)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="kgs-app", description="Kinematics-GS: dynamic Gaussians from blurry video.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="the main job: synthesize the built-in scene, train (fast preset), evaluate, serve")
    p.add_argument("--workspace", default="workspace", help="folder for the demo's scene and run")
    p.add_argument("--iterations", type=positive_int, help="override the preset's iteration count (its schedule scales with it)")
    p.add_argument("--retrain", action="store_true")
    p.add_argument("--no-serve", action="store_true", help="stop after evaluating instead of serving the viewer")
    p.add_argument("--port", type=int, default=8000)
    p.set_defaults(func=cmd_demo)

    from kgs_core.job_options import ExportOptions, IngestOptions, SynthOptions, TrainOptions

    p = sub.add_parser("synth", help="render a synthetic blurry dynamic scene with ground truth")
    add_options(p, SynthOptions, positional=("name",))
    p.add_argument("--out", required=True, help="dataset folder to create")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("ingest", help="structure from motion on a (blurry) video -> scene folder")
    p.add_argument("video")
    p.add_argument("--eval-video", help="a synchronised second video: registered as held-out test views")
    p.add_argument("--out", required=True)
    add_options(p, IngestOptions)
    p.add_argument(
        "--no-cache",
        action="store_true",
        help="do not reuse or keep decoded frames, features, matches and poses (cache: $KGS_CACHE_DIR or ~/.cache/kinematics-gs)",
    )
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_ingest)

    from kgs_core.train.config import ABLATIONS, PRESETS

    p = sub.add_parser("train", help="train Kinematics-GS on a scene folder")
    p.add_argument("scene", help="dataset folder (Nerfies, D-NeRF or COLMAP layout)")
    p.add_argument("--out", required=True, help="run directory")
    add_options(
        p,
        TrainOptions,
        flags={"settings": "--set"},
        metavars={"settings": "KEY=VALUE", "ablate": "PART"},
        extra_help={
            "preset": f" (one of {', '.join(sorted(PRESETS))})",
            "ablate": ": " + ", ".join(f"{k} ({v})" for k, v in ABLATIONS.items()),
            "settings": "; e.g. --set lambda_reg=0.02 --set model.knn=16",
        },
    )
    p.add_argument("--resume", action="store_true", help="continue from the run's last checkpoint")
    p.add_argument(
        "--init-from",
        metavar="RUN",
        help="start from this run directory's final model (fine-tuning), decomposed at this run's τ, instead of from points",
    )
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("train-many", help="train scenes x presets x configurations x seeds, in turn or as Ray tasks (--ray)")
    p.add_argument("scenes", nargs="+", help="scene folders")
    p.add_argument(
        "--out",
        required=True,
        help="workspace folder: runs go to OUT/runs/SCENE-PRESET-CONFIG-sSEED (with --ray on a cluster, a folder every node mounts)",
    )
    p.add_argument("--presets", default="fast", help="comma-separated, of: " + ", ".join(sorted(PRESETS)))
    p.add_argument(
        "--configs",
        default="full",
        help="comma-separated configurations, as for bench quality (full, decompose, deform, cf, ..., NAME@KEY=VALUE)",
    )
    p.add_argument("--seeds", default="0", help="comma-separated training seeds")
    p.add_argument("--iterations", type=positive_int, help="override every preset's iteration count")
    from .cluster import add_ray_options

    add_ray_options(p)
    p.set_defaults(func=cmd_train_many)

    p = sub.add_parser("eval", help="evaluate a run: PSNR/SSIM (+ in the dynamic mask), decomposition IoU, FPS per LoD")
    p.add_argument("run")
    p.add_argument("--scene", help="scene folder (default: the one the run was trained on)")
    p.add_argument(
        "--device",
        default="auto",
        help="where to render: auto (CUDA when torch sees a GPU, with gsplat: pip install 'kinematics-gs[cuda]'), cpu, cuda",
    )
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("export", help="export a run: per-frame .ply/.splat, .splatv, mp4 video, .glb ellipsoids")
    p.add_argument("run", help="run directory")
    add_options(p, ExportOptions)
    p.add_argument(
        "--keyframes",
        metavar="FILE",
        help="mp4: a camera path of JSON keyframes (kgs_core/export/camera_path.py documents the format), instead of --camera-path",
    )
    p.add_argument("--out", help="output file or folder (default: RUN/exports/...)")
    p.add_argument("--force", action="store_true", help="replace an existing output")
    p.set_defaults(func=cmd_export)

    p = sub.add_parser("serve", help="serve runs to the browser viewer: REST, WebSocket splat streams, live tau")
    p.add_argument("paths", nargs="*", help="scene folders or run directories to add to the workspace")
    p.add_argument("--workspace", default="workspace", help="workspace folder (created if missing)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind; anything but loopback needs a token")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--token", help="access token for the API (generated when binding beyond loopback)")
    p.add_argument("--cors", action="append", metavar="ORIGIN", help="allow this browser origin (CORS is off by default)")
    p.add_argument(
        "--allow-host",
        action="append",
        metavar="NAME",
        help="also answer requests whose Host is NAME (behind a reverse proxy; default: the bound address and loopback names)",
    )
    p.add_argument("--max-upload-mb", type=int, default=512)
    p.add_argument("--demo", action="store_true", help="in an empty workspace, make and train the demo scene")
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("view", help="desktop viewer (imgui + moderngl): a run directory, or a run on a server")
    p.add_argument("run", nargs="?", help="run directory (omit with --server)")
    p.add_argument("--server", help="URL of a running kgs-app serve, e.g. http://127.0.0.1:8000")
    p.add_argument("--run-id", help="the run's id on --server")
    p.add_argument("--token", help="access token of --server")
    p.add_argument("--time", type=float, default=0.0, help="initial time in [0, 1]")
    p.add_argument("--frame", type=int, help="start from this scene frame's camera")
    p.add_argument("--overlay", type=int, default=0, choices=[0, 1, 2], help="0 colours, 1 tint, 2 velocity ellipses")
    p.add_argument("--screenshot", help="save the view as PNG (with --frames or --offscreen)")
    p.add_argument("--frames", type=int, help="close the window after this many frames (scripted use)")
    p.add_argument("--offscreen", action="store_true", help="no window: render one image with EGL (headless)")
    p.set_defaults(func=cmd_view)

    p = sub.add_parser("build-ext", help="compile the C++ CPU rasteriser (cached after the first time)")
    p.add_argument("--verbose", action="store_true")
    p.set_defaults(func=cmd_build_ext)

    p = sub.add_parser("bench", help="benchmarks that print numbers (results: docs/results.md)")
    p.add_argument(
        "what",
        choices=BENCHMARKS,
        help="raster: rasteriser timings and a raster-only training step; step: the whole model's "
        "training step at the demo scale, by phase; serve: scrubbing latency, 50 clients; "
        "stability: float32 vs float64 and training on extreme sequences; quality: each "
        "ablation and baseline on the same time budget, tau sweep; real: the shared real clips "
        "against the baselines; threads: training alone, two at once and beside a busy "
        "process under each OpenMP setting; gpu: gsplat on CUDA against the CPU rasteriser (difference, FPS)",
    )
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options of the benchmark (--help for them)")
    p.set_defaults(func=cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    from kgs_core.threads import configure_process

    configure_process()  # before anything imports torch: OpenMP reads its settings once
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileExistsError, FileNotFoundError) as exc:  # SceneError is a ValueError
        print(f"kgs-app {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
