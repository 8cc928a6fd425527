"""Nerfies / HyperNeRF / NeRF-DS layout.

```
dataset.json   {"count", "num_exemplars", "ids", "train_ids", "val_ids"}
metadata.json  {id: {"warp_id", "appearance_id", "camera_id", "time_id"}}
scene.json     {"scale", "center", "near", "far"}
camera/ID.json {"orientation" (world-to-camera R), "position" (centre), "focal_length",
                "principal_point", "skew", "pixel_aspect_ratio", "radial_distortion",
                "tangential_distortion", "image_size"}
rgb/{s}x/ID.png
points.npy     optional SfM points (P, 3)
```

Extensions written and read by Kinematics-GS (ignored by other tools): per-frame `time` and
`exposure` in metadata.json, ground truth under `sharp/{s}x/`, `mask/{s}x/`, `motion/{s}x/`,
`point_colors.npy`, and `kgs.json` (what produced the scene).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scene import Camera, Frame, Normalization, Scene, SceneError
from .common import copy_into, field, find_image, inside, matrix, number, read_json, write_json


def is_nerfies(root: Path) -> bool:
    return (root / "dataset.json").is_file()


MAX_IMAGE_SIDE = 16384


def _camera(path: Path, scale: int) -> Camera:
    where = str(path)
    js = read_json(path)
    R = matrix(field(js, "orientation", where), (3, 3), where, "orientation")
    pos = matrix(field(js, "position", where), (3,), where, "position")
    f = number(js, "focal_length", where, positive=True)
    pp = matrix(field(js, "principal_point", where), (2,), where, "principal_point")
    size = matrix(field(js, "image_size", where), (2,), where, "image_size")
    if not all(1 <= v <= MAX_IMAGE_SIDE and v == int(v) for v in size):
        raise SceneError(f"{where}: field 'image_size' should be two whole numbers in 1..{MAX_IMAGE_SIDE}, got {size.tolist()}")
    aspect = number(js, "pixel_aspect_ratio", where, 1.0, positive=True)
    skew = number(js, "skew", where, 0.0)
    radial = matrix(js.get("radial_distortion", [0.0, 0.0, 0.0]), (3,), where, "radial_distortion")
    tangential = matrix(js.get("tangential_distortion", [0.0, 0.0]), (2,), where, "tangential_distortion")
    K = np.array([[f, skew, pp[0]], [0.0, f * aspect, pp[1]], [0.0, 0.0, 1.0]])
    viewmat = np.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ pos
    cam = Camera(
        K=K,
        viewmat=viewmat,
        width=int(size[0]),
        height=int(size[1]),
        distortion=np.array([radial[0], radial[1], tangential[0], tangential[1], radial[2]], dtype=float),
    )
    return cam.scaled(1.0 / scale) if scale != 1 else cam


def load_nerfies(root: Path, scale: int = 1) -> Scene:
    root = Path(root)
    ds = read_json(root / "dataset.json")
    where = str(root / "dataset.json")
    ids = [str(i) for i in field(ds, "ids", where, list)]
    train_ids = {str(i) for i in (field(ds, "train_ids", where, list) if "train_ids" in ds else ids)}
    val_ids = {str(i) for i in (field(ds, "val_ids", where, list) if "val_ids" in ds else [])}
    unknown = (train_ids | val_ids) - set(ids)
    if unknown:
        raise SceneError(f"{where}: train_ids/val_ids name unknown ids {sorted(unknown)[:3]}")
    meta_path = root / "metadata.json"
    meta = read_json(meta_path) if meta_path.is_file() else {}
    if not isinstance(meta, dict) or not all(isinstance(v, dict) for v in meta.values()):
        raise SceneError(f"{meta_path}: expected an object of per-frame objects")
    rgb_dir = root / "rgb" / f"{scale}x"
    if not rgb_dir.is_dir():
        raise SceneError(f"missing image folder {rgb_dir}")

    warp = {}
    for i in ids:
        m = meta.get(i, {})
        warp[i] = m.get("time_id", m.get("warp_id"))
    explicit_time = all("time" in meta.get(i, {}) for i in ids)
    if not explicit_time:
        missing = [i for i in ids if warp[i] is None]
        if missing:
            raise SceneError(f"{meta_path}: frame {missing[0]} has no 'time', 'time_id' or 'warp_id'")
        warp = {i: number(meta[i], "time_id" if "time_id" in meta[i] else "warp_id", f"{meta_path} frame {i!r}") for i in ids}
        max_warp = max(warp.values()) or 1

    frames = []
    for i in ids:
        m = meta.get(i, {})
        w = f"{meta_path} frame {i!r}"
        t = number(m, "time", w) if explicit_time else warp[i] / max_warp
        cam = _camera(inside(root, f"camera/{i}.json", f"{where} id {i!r}"), scale)
        split = "test" if i in val_ids and i not in train_ids else "train"

        def extra(kind: str, ext: str) -> Path | None:
            p = inside(root, f"{kind}/{scale}x/{i}{ext}", f"{where} id {i!r}")
            return p if p.is_file() else None

        frames.append(
            Frame(
                id=i,
                image_path=find_image(root, f"rgb/{scale}x/{i}", f"{where} id {i!r}"),
                time=t,
                camera=cam,
                exposure=number(m, "exposure", w, 0.0),
                split=split,
                camera_id=number(m, "camera_id", w, 0, integer=True),
                sharp_path=extra("sharp", ".png"),
                mask_path=extra("mask", ".png"),
                motion_path=extra("motion", ".npy"),
            )
        )
    # `ids` is the capture order: a time that goes backwards along it is an error (raised by
    # Scene's validation, prefixed with the file that holds the times below).

    points, colors = np.zeros((0, 3)), np.zeros((0, 3))
    if (root / "points.npy").is_file():
        try:
            points = np.load(root / "points.npy", allow_pickle=False).astype(np.float64)
        except (ValueError, OSError) as exc:
            raise SceneError(f"{root / 'points.npy'}: {exc}") from None
        if points.ndim != 2 or points.shape[1] != 3:
            raise SceneError(f"{root / 'points.npy'}: expected (P, 3), got {points.shape}")
        colors = np.full_like(points, 0.5)
        if (root / "point_colors.npy").is_file():
            colors = np.load(root / "point_colors.npy", allow_pickle=False).astype(np.float64)
            if colors.shape != points.shape:
                raise SceneError(f"{root / 'point_colors.npy'}: shape {colors.shape} does not match points {points.shape}")

    norm = Normalization()
    if (root / "scene.json").is_file():
        sc = read_json(root / "scene.json")
        where_sc = str(root / "scene.json")
        if not isinstance(sc, dict):
            raise SceneError(f"{where_sc}: expected a JSON object")
        norm = Normalization(
            center=matrix(sc.get("center", [0, 0, 0]), (3,), where_sc, "center"), scale=number(sc, "scale", where_sc, 1.0, positive=True)
        )
    extras = read_json(root / "kgs.json") if (root / "kgs.json").is_file() else {}
    if not isinstance(extras, dict):
        raise SceneError(f"{root / 'kgs.json'}: expected a JSON object")
    try:
        return Scene(
            name=root.name,
            root=root,
            frames=frames,
            points=points,
            point_colors=colors,
            normalization=norm,
            source_format="nerfies",
            extras=extras,
        )
    except SceneError as exc:
        raise SceneError(f"{meta_path}: {exc}") from None


def camera_json(cam: Camera) -> dict:
    R, t = cam.viewmat[:3, :3], cam.viewmat[:3, 3]
    d = cam.distortion
    return {
        "orientation": R.tolist(),
        "position": (-R.T @ t).tolist(),
        "focal_length": float(cam.K[0, 0]),
        "principal_point": [float(cam.K[0, 2]), float(cam.K[1, 2])],
        "skew": float(cam.K[0, 1]),
        "pixel_aspect_ratio": float(cam.K[1, 1] / cam.K[0, 0]),
        "radial_distortion": [float(d[0]), float(d[1]), float(d[4])],
        "tangential_distortion": [float(d[2]), float(d[3])],
        "image_size": [cam.width, cam.height],
    }


def write_nerfies(scene: Scene, root: Path) -> None:
    """Writes `scene` in the Nerfies layout under `root` (images copied if they live elsewhere).
    The scene's coordinates are written as they are; scene.json records its normalisation."""
    root = Path(root)
    ids = [f.id for f in scene.frames]
    write_json(
        root / "dataset.json",
        {
            "count": len(ids),
            "num_exemplars": len(scene.train_frames),
            "ids": ids,
            "train_ids": [f.id for f in scene.train_frames],
            "val_ids": [f.id for f in scene.test_frames],
        },
    )
    by_cam: dict[int, list[Frame]] = {}
    for f in scene.frames:
        by_cam.setdefault(f.camera_id, []).append(f)
    meta = {}
    for frames in by_cam.values():
        for k, f in enumerate(sorted(frames, key=lambda f: f.time)):
            meta[f.id] = {"warp_id": k, "appearance_id": k, "camera_id": f.camera_id, "time_id": k, "time": f.time, "exposure": f.exposure}
    write_json(root / "metadata.json", meta)
    centers = np.stack([f.camera.center for f in scene.frames])
    dist = np.linalg.norm(centers, axis=1)
    write_json(
        root / "scene.json",
        {**scene.normalization.to_dict(), "near": float(max(dist.min() * 0.05, 1e-3)), "far": float(dist.max() * 4 + 1)},
    )
    for f in scene.frames:
        write_json(root / "camera" / f"{f.id}.json", camera_json(f.camera))
        copy_into(f.image_path, root / "rgb" / "1x" / f"{f.id}{f.image_path.suffix}")
        for kind, p in (("sharp", f.sharp_path), ("mask", f.mask_path), ("motion", f.motion_path)):
            if p is not None:
                copy_into(p, root / kind / "1x" / f"{f.id}{p.suffix}")
    if len(scene.points):
        np.save(root / "points.npy", scene.points)
        np.save(root / "point_colors.npy", scene.point_colors)
    if scene.extras:
        write_json(root / "kgs.json", scene.extras)
