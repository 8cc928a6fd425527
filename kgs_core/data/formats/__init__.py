"""Dataset formats: readers with auto-detection, and writers for the layouts we produce."""

from __future__ import annotations

from pathlib import Path

from ..scene import Scene, SceneError
from .colmap import is_colmap, load_colmap, write_colmap
from .common import files_inside, json_object_file
from .dnerf import is_dnerf, load_dnerf, write_dnerf
from .nerfies import is_nerfies, load_nerfies, write_nerfies

FORMATS = ("nerfies", "dnerf", "colmap")


def detect_format(root: Path) -> str:
    root = Path(root)
    if not root.exists():
        raise SceneError(f"dataset not found: {root}")
    if not root.is_dir():
        raise SceneError(f"{root} is a file; a dataset is a folder (for a video use `kgs-app ingest`)")
    if is_nerfies(root):
        return "nerfies"
    if is_dnerf(root):
        return "dnerf"
    if is_colmap(root):
        return "colmap"
    raise SceneError(
        f"{root}: unknown dataset layout (looked for dataset.json [Nerfies], transforms_train.json [D-NeRF], sparse/0/cameras.bin [COLMAP])"
    )


def load_scene(root: str | Path, fmt: str = "auto", normalize: bool = True) -> Scene:
    """Reads a dataset folder in any supported format, normalised to a unit-ish sphere unless
    `normalize=False` (scenes we wrote are already normalised and keep their coordinates)."""
    root = Path(root)
    fmt = detect_format(root) if fmt == "auto" else fmt
    if fmt == "nerfies":
        scene = load_nerfies(root)
    elif fmt == "dnerf":
        scene = load_dnerf(root)
    elif fmt == "colmap":
        scene = load_colmap(root)
    else:
        raise SceneError(f"unknown format {fmt!r}; choose from auto, {', '.join(FORMATS)}")
    files_inside(scene, root)
    if not scene.extras and (root / "kgs.json").is_file():
        scene.extras = json_object_file(root / "kgs.json")
    if normalize and not scene.extras.get("normalized", False):
        scene.normalize()
    return scene


__all__ = ["load_scene", "detect_format", "write_nerfies", "write_dnerf", "write_colmap", "FORMATS"]
