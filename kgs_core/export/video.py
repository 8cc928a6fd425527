"""Video export: render a camera path over a time range (sharp, or with the kinematic blur of an
exposure), optionally beside the input frames, and encode H.264 mp4."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.video import encode_video
from ..progress import progress_bar
from .bake import ExportSource, bake, render_baked
from .camera_path import PathStep


def _to_uint8(img: np.ndarray) -> np.ndarray:
    return (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    from PIL import Image

    if img.shape[:2] == (h, w):
        return img
    return np.asarray(Image.fromarray(img).resize((w, h), Image.BILINEAR))


def render_path(
    source: ExportSource,
    steps: list[PathStep],
    exposure: float = 0.0,
    side_by_side: bool = False,
    background: np.ndarray | None = None,
    progress: bool = True,
) -> list[np.ndarray]:
    frames = []
    static = None if source.moves else bake(source, 0.0, exposure)  # a static scene is baked once
    for step in progress_bar(steps, desc="render video", show=progress):
        g = static if static is not None else bake(source, step.time, exposure)
        img = _to_uint8(render_baked(g, step.camera, source.sh_degree, background).image.numpy())
        if side_by_side:
            if step.frame is None:
                raise ValueError("--side-by-side needs the training camera path (input frames to show)")
            inp = _resize(_to_uint8(step.frame.image()), img.shape[0], img.shape[1])
            img = np.concatenate([inp, img], axis=1)
        frames.append(img)
    return frames


def write_video(path: str | Path, frames: list[np.ndarray], fps: float, progress: bool = True) -> Path:
    return encode_video(frames, path, fps=fps, progress=progress)
