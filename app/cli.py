"""`kgs-app`: the command line of Kinematics-GS. Every command listed here works."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path


def cmd_demo(args: argparse.Namespace) -> int:
    """Smoke demo until the reconstruction pipeline lands: render a random Gaussian scene."""
    import numpy as np
    import torch
    from PIL import Image

    from kgs_core.io import atomic_write_bytes
    from kgs_core.render import rasterize, resolve_backend
    from kgs_core.render.random_scene import random_scene

    backend = resolve_backend("auto")
    scene = random_scene(args.n, args.size, args.size, overlap=20.0, seed=args.seed)
    t0 = time.perf_counter()
    with torch.no_grad():
        out = rasterize(scene.means, scene.opacities, scene.viewmat, scene.K, args.size, args.size,
                        quats=scene.quats, scales=scene.scales, colors=scene.colors,
                        background=torch.ones(3), backend=backend)
    ms = (time.perf_counter() - t0) * 1e3
    img = (out.image.clamp(0, 1).numpy() * 255).round().astype(np.uint8)
    import io

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    path = Path(args.out)
    atomic_write_bytes(path, buf.getvalue())
    print(f"rendered {args.n:,} Gaussians at {args.size}x{args.size} with the {backend} backend in {ms:.1f} ms -> {path}")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    """Render a named synthetic scene with ground truth to a dataset folder."""
    from kgs_core.data.synth.generate import synthesize

    out = synthesize(args.name, args.out, blur=args.blur, seed=args.seed, size=args.size, frames=args.frames,
                     subframes=args.subframes, overwrite=args.overwrite)
    print(f"wrote {out} (Nerfies + D-NeRF layouts, ground truth under sharp/, mask/, motion/)")
    return 0


def cmd_ingest(args: argparse.Namespace) -> int:
    """Video -> frames -> sharpness -> pycolmap SfM -> Nerfies-layout scene."""
    from kgs_core.data.ingest import ingest

    rep = ingest(args.video, args.out, eval_video=args.eval_video, every=args.every, max_frames=args.max_frames,
                 max_size=args.max_size, exposure=args.exposure, overwrite=args.overwrite)
    print(f"registered {rep.registered}/{rep.frames} training frames"
          + (f", {rep.eval_registered}/{rep.eval_frames} held-out frames" if rep.eval_video else "")
          + f"; mean reprojection error {rep.mean_reprojection_error_px:.2f} px; {rep.points} points; "
          f"times {rep.seconds} -> {args.out}")
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
    print(f"C++ rasteriser ready in {time.perf_counter() - t0:.1f} s: {mod.__file__}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    if args.what == "raster":
        from kgs_app.bench.raster import main as bench_main

        return bench_main(args.rest)
    raise AssertionError(args.what)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="kgs-app", description="Kinematics-GS: dynamic Gaussians from blurry video.")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("demo", help="render a random Gaussian scene to a PNG (smoke demo)")
    p.add_argument("--out", default="out/demo.png")
    p.add_argument("--n", type=int, default=20_000, help="number of Gaussians")
    p.add_argument("--size", type=int, default=256, help="image width and height")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=cmd_demo)

    from kgs_core.data.synth.generate import BLUR_LEVELS, DEFAULT_SCENE
    from kgs_core.data.synth.scenes import SCENES

    p = sub.add_parser("synth", help="render a synthetic blurry dynamic scene with ground truth")
    p.add_argument("name", nargs="?", default=DEFAULT_SCENE, choices=sorted(SCENES))
    p.add_argument("--out", required=True, help="dataset folder to create")
    p.add_argument("--blur", default="mild", choices=list(BLUR_LEVELS), help="exposure 0, 0.5 or 1 frame interval")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=int, default=128, help="image width and height")
    p.add_argument("--frames", type=int, default=60)
    p.add_argument("--subframes", type=int, default=16, help="sharp renders averaged per blurry frame")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("ingest", help="structure from motion on a (blurry) video -> scene folder")
    p.add_argument("video")
    p.add_argument("--eval-video", help="a synchronised second video: registered as held-out test views")
    p.add_argument("--out", required=True)
    p.add_argument("--every", type=int, default=1, help="keep every k-th frame")
    p.add_argument("--max-frames", type=int)
    p.add_argument("--max-size", type=int, default=960, help="downscale so the long side is at most this")
    p.add_argument("--exposure", type=float, default=0.5, help="assumed shutter fraction of the training video")
    p.add_argument("--overwrite", action="store_true")
    p.set_defaults(func=cmd_ingest)

    p = sub.add_parser("build-ext", help="compile the C++ CPU rasteriser (cached after the first time)")
    p.add_argument("--verbose", action="store_true")
    p.set_defaults(func=cmd_build_ext)

    p = sub.add_parser("bench", help="benchmarks that print numbers (see docs/performance.md)")
    p.add_argument("what", choices=["raster"], help="raster: rasteriser and training-step timings")
    p.add_argument("rest", nargs=argparse.REMAINDER, help="options of the benchmark (--help for them)")
    p.set_defaults(func=cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, FileExistsError, FileNotFoundError) as exc:  # SceneError is a ValueError
        print(f"kgs-app {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
