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
    except RecursionError:
        raise SceneError(f"{path}: JSON nested too deeply") from None


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


def number(obj: dict, key: str, where: str, default=None, *, integer: bool = False, positive: bool = False):
    """`obj[key]` (or `default` when absent) as a finite float (or int), with an error naming
    the file and the field when it is anything else (null, a list, a string, NaN, ...)."""
    if not isinstance(obj, dict):
        raise SceneError(f"{where}: expected a JSON object, got {type(obj).__name__}")
    if key not in obj and default is not None:
        return default
    val = field(obj, key, where)
    if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val):
        raise SceneError(f"{where}: field '{key}' should be a finite number, got {json.dumps(val)[:40]}")
    if integer:
        if float(val) != int(val) or abs(val) > 2**31:
            raise SceneError(f"{where}: field '{key}' should be a whole number, got {val}")
        val = int(val)
    if positive and val <= 0:
        raise SceneError(f"{where}: field '{key}' should be positive, got {val}")
    return int(val) if integer else float(val)


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


def inside(root: Path, rel: str | Path, where: str) -> Path:
    """`root / rel` resolved (symlinks followed), refused unless it stays inside `root`: a
    dataset may name only its own files (an absolute path, `../` or a symlink out of the folder
    would let an uploaded dataset read any file the server can). The message names the field,
    never whether the outside path exists."""
    base = Path(root).resolve()
    if Path(rel).is_absolute():
        raise SceneError(f"{where}: absolute path {str(rel)!r} (paths must be relative to the dataset folder)")
    path = (base / rel).resolve()
    if path != base and base not in path.parents:
        raise SceneError(f"{where}: path {str(rel)!r} leaves the dataset folder")
    return path


def files_inside(scene, root: Path) -> None:
    """Every file a loaded scene will read (images, sharp frames, masks, motion) lies inside
    the dataset folder: the one check every reader's output passes (`load_scene`), so that a
    reader that forgot `inside` still cannot serve a file from elsewhere."""
    base = Path(root).resolve()
    for frame in scene.frames:
        for kind in ("image_path", "sharp_path", "mask_path", "motion_path"):
            path = getattr(frame, kind)
            if path is not None and not Path(path).resolve().is_relative_to(base):
                raise SceneError(f"{base.name}: frame {frame.id!r}: its {kind.removesuffix('_path')} leaves the dataset folder")


def json_object_file(path: Path) -> dict:
    """A JSON file that must hold an object, with an error naming it otherwise."""
    obj = read_json(path)
    if not isinstance(obj, dict):
        raise SceneError(f"{path.name}: expected a JSON object, got {type(obj).__name__}")
    return obj


def find_image(root: Path, rel: str | Path, where: str) -> Path:
    """`root / rel` if it is a file, else with a common image extension added; every candidate
    must stay inside `root` (`inside`)."""
    for cand in (str(rel), *(str(rel) + ext for ext in IMAGE_EXTS)):
        path = inside(root, cand, where)
        if path.is_file():
            return path
    raise SceneError(f"{where}: image not found: {rel} (tried {', '.join(IMAGE_EXTS)})")


def image_size(path: Path) -> tuple[int, int]:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError, Image.DecompressionBombError) as exc:
        raise SceneError(f"cannot read image {path}: {exc}") from None


def copy_into(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    if src.resolve() != dst.resolve():
        shutil.copyfile(src, dst)
