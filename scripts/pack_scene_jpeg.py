"""A copy of a scene folder with its frames as JPEG (quality 95), to carry a full-size ingest to a
machine where the working tree that travels is size-limited (scripts/gpu_check.sh): walk at
960 px is 51 MB of PNG and about 15 MB of JPEG. The scene readers take either extension.

Usage: python3 scripts/pack_scene_jpeg.py SCENE OUT
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from PIL import Image


def main(src: Path, dst: Path) -> None:
    if dst.exists():
        raise SystemExit(f"{dst} exists")
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.png"))
    for png in sorted(src.rglob("*.png")):
        out = (dst / png.relative_to(src)).with_suffix(".jpg" if png.parts[-3] == "rgb" else ".png")
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.suffix == ".jpg":
            Image.open(png).convert("RGB").save(out, quality=95)
        else:  # masks and other exact images stay lossless
            shutil.copy2(png, out)
    print(f"{dst}: {sum(p.stat().st_size for p in dst.rglob('*') if p.is_file()) / 1e6:.1f} MB")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit(__doc__)
    main(Path(sys.argv[1]), Path(sys.argv[2]))
