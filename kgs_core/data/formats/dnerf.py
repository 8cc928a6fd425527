"""D-NeRF layout: `transforms_{train,val,test}.json` with per-frame `time` and a camera-to-world
`transform_matrix` in the Blender/OpenGL convention (x right, y up, z backward).

Extensions (ignored by other tools): per-frame `exposure`, `camera_id`, `id`, and
`sharp_file_path` / `mask_file_path` / `motion_file_path` for ground truth. D-NeRF cannot
express a principal point off the image centre or distortion; the writer refuses such cameras.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..scene import Camera, Frame, Scene, SceneError
from .common import field, find_image, image_size, inside, matrix, number, read_json, write_json

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])
SPLITS = {"train": "train", "val": "test", "test": "test"}


def is_dnerf(root: Path) -> bool:
    return (root / "transforms_train.json").is_file()


def load_dnerf(root: Path) -> Scene:
    root = Path(root)
    frames: list[Frame] = []
    for split_file, split in SPLITS.items():
        path = root / f"transforms_{split_file}.json"
        if not path.is_file():
            continue
        js = read_json(path)
        where = str(path)
        angle = number(js, "camera_angle_x", where, positive=True)
        if angle >= math.pi:
            raise SceneError(f"{where}: field 'camera_angle_x' should be below pi (radians), got {angle}")
        entries = field(js, "frames", where, list)
        for k, fr in enumerate(entries):
            w = f"{where} frames[{k}]"
            rel = field(fr, "file_path", w, str)
            img = find_image(root, rel, f"{w} field 'file_path'")
            time = number(fr, "time", w)
            c2w = matrix(field(fr, "transform_matrix", w), (4, 4), w, "transform_matrix") @ GL_TO_CV
            width, height = image_size(img)
            fx = 0.5 * width / math.tan(0.5 * angle)
            K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
            viewmat = np.linalg.inv(c2w)
            viewmat[3] = (0, 0, 0, 1)

            def extra(key: str) -> Path | None:
                return inside(root, field(fr, key, w, str), f"{w} field '{key}'") if key in fr else None

            frames.append(
                Frame(
                    id=str(fr.get("id", f"{split_file}_{k:04d}")),
                    image_path=img,
                    time=time,
                    camera=Camera(K=K, viewmat=viewmat, width=width, height=height),
                    exposure=number(fr, "exposure", w, 0.0),
                    split=split,
                    camera_id=number(fr, "camera_id", w, 0 if split == "train" else 1, integer=True),
                    sharp_path=extra("sharp_file_path"),
                    mask_path=extra("mask_file_path"),
                    motion_path=extra("motion_file_path"),
                )
            )
    if not frames:
        raise SceneError(f"{root}: no frames in transforms_*.json")
    # val and test often repeat the same frames: keep one of each id.
    seen, unique = set(), []
    for f in frames:
        if f.id not in seen:
            seen.add(f.id)
            unique.append(f)
    unique.sort(key=lambda f: (f.camera_id, f.time, f.id))
    return Scene(name=root.name, root=root, frames=unique, source_format="dnerf")


def write_dnerf(scene: Scene, root: Path) -> None:
    """Writes transforms_train.json / transforms_test.json pointing at images already under
    `root` (write the Nerfies layout first, or copy images there)."""
    root = Path(root)
    for split, frames in (("train", scene.train_frames), ("test", scene.test_frames)):
        if not frames:
            continue
        cam0 = frames[0].camera
        angle = 2 * math.atan(0.5 * cam0.width / cam0.K[0, 0])
        entries = []
        for f in frames:
            c = f.camera
            if abs(c.K[0, 2] - c.width / 2) > 1e-6 or abs(c.K[1, 2] - c.height / 2) > 1e-6 or np.any(c.distortion != 0):
                raise SceneError(f"frame {f.id}: D-NeRF cannot store an off-centre principal point or distortion")
            if abs(c.K[0, 0] - cam0.K[0, 0]) > 1e-6 or abs(c.K[1, 1] - c.K[0, 0]) > 1e-6:
                raise SceneError(f"frame {f.id}: D-NeRF needs one square-pixel focal length per split")
            c2w = np.linalg.inv(c.viewmat) @ GL_TO_CV
            entry = {
                "file_path": _rel(f.image_path, root),
                "time": f.time,
                "transform_matrix": c2w.tolist(),
                "id": f.id,
                "exposure": f.exposure,
                "camera_id": f.camera_id,
            }
            for key, p in (("sharp_file_path", f.sharp_path), ("mask_file_path", f.mask_path), ("motion_file_path", f.motion_path)):
                if p is not None:
                    entry[key] = _rel(p, root)
            entries.append(entry)
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": angle, "frames": entries})


def _rel(path: Path, root: Path) -> str:
    try:
        return "./" + str(Path(path).resolve().relative_to(root.resolve()))
    except ValueError:
        raise SceneError(f"{path} is not inside {root}: D-NeRF paths are relative") from None
