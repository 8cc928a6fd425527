"""Derives the small real-footage test fixture (tests/fixtures/walk96) from an ingested clip:
every K-th frame of both cameras, images shrunk to a given width, cameras scaled to match, the
SfM points and poses kept.

    kgs-app ingest ../shared/data/bardgs/walk_blur.mp4 --eval-video ../shared/data/bardgs/walk_sharp.mp4 \\
        --out walk320 --max-size 320
    python scripts/make_real_fixture.py walk320 tests/fixtures/walk96 --every 3 --width 96
"""

from __future__ import annotations

import argparse
import tempfile
from dataclasses import replace
from pathlib import Path

from PIL import Image

from kgs_core.data.formats import load_scene, write_nerfies
from kgs_core.data.scene import Scene
from kgs_core.io import atomic_directory


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("out")
    ap.add_argument("--every", type=int, default=3)
    ap.add_argument("--width", type=int, default=96)
    args = ap.parse_args()
    scene = load_scene(args.scene)
    frames = []
    with tempfile.TemporaryDirectory() as tmp:
        for cam_frames in (scene.train_frames, scene.test_frames):
            for f in cam_frames[:: args.every]:
                img = Image.open(f.image_path).convert("RGB")
                factor = args.width / img.width
                small = img.resize((args.width, round(img.height * factor)), Image.Resampling.LANCZOS)
                path = Path(tmp) / f"{f.id}.png"
                small.save(path, optimize=True)
                cam = f.camera.scaled(factor)
                frames.append(replace(f, image_path=path, camera=replace(cam, height=small.height)))
        out = Scene(
            name=Path(args.out).name,
            root=Path(args.out),
            frames=frames,
            points=scene.points,
            point_colors=scene.point_colors,
            normalization=scene.normalization,
            source_format="nerfies",
            extras={
                **scene.extras,
                "normalized": True,
                "derived_from": {"scene": Path(args.scene).name, "every": args.every, "width": args.width},
            },
        )
        with atomic_directory(Path(args.out), overwrite=True) as dst:
            write_nerfies(out, dst)
    print(f"wrote {args.out}: {len(frames)} frames at {args.width} px")


if __name__ == "__main__":
    main()
