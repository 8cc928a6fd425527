"""Helpers shared by the dataset readers and writers."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from ...io import atomic_write_text
from ..scene import SceneError

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".JPG", ".PNG", ".webp")


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneError(f"missing file: {path}") from None
    except json.JSONDecodeError as exc:
        raise SceneError(f"{path}: invalid JSON ({exc.msg} at line {exc.lineno})") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a UTF-8 text file") from None


def write_json(path: Path, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=1))


def field(obj: dict, key: str, where: str, kind=None):
    """`obj[key]`, with an error naming the file and the field when missing or mistyped."""
    if not isinstance(obj, dict) or key not in obj:
        raise SceneError(f"{where}: missing field '{key}'")
    val = obj[key]
    if kind is not None and not isinstance(val, kind):
        raise SceneError(f"{where}: field '{key}' should be {getattr(kind, '__name__', kind)}, got {type(val).__name__}")
    return val


def matrix(val, shape: tuple[int, ...], where: str, name: str) -> np.ndarray:
    try:
        arr = np.asarray(val, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(f"{where}: field '{name}' is not numeric") from None
    if arr.shape != shape:
        raise SceneError(f"{where}: field '{name}' should have shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise SceneError(f"{where}: field '{name}' has non-finite values")
    return arr


def find_image(base: Path) -> Path:
    """`base` itself if it exists, else `base` with a common image extension."""
    if base.is_file():
        return base
    for ext in IMAGE_EXTS:
        cand = base.with_name(base.name + ext)
        if cand.is_file():
            return cand
    raise SceneError(f"image not found: {base} (tried {', '.join(IMAGE_EXTS)})")


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError) as exc:
        raise SceneError(f"cannot read image {path}: {exc}") from None


def copy_into(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.resolve() != dst.resolve():
        shutil.copyfile(src, dst)
