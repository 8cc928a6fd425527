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
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
