"""COLMAP sparse model (`sparse/0/` or `sparse/`, binary or text) plus `images/`, read with
pycolmap. Frames are ordered in time by image name; times are spread evenly over [0, 1]
unless `times.json` says otherwise: `{image name: t}` or `{image name: {"time": t,
"camera_id": c, "split": "train"|"test", "exposure": e}}` (our writer uses the second form)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..scene import Camera, Frame, Scene, SceneError
from .common import inside, number, read_json

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")


def model_dir(root: Path) -> Path | None:
    for cand in (root / "sparse" / "0", root / "sparse", root):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    return None


def is_colmap(root: Path) -> bool:
    return model_dir(root) is not None


def camera_from_colmap(cam, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(K, distortion k1 k2 p1 p2 k3) of a pycolmap camera."""
    name = cam.model_name if hasattr(cam, "model_name") else str(cam.model)
    name = name.split(".")[-1]
    p = list(cam.params)
    dist = np.zeros(5)
    if name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
    elif name == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        fx = fy = f
        dist[0] = k
    elif name == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
        dist[:2] = (k1, k2)
    elif name == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        dist[:4] = (k1, k2, p1, p2)
    else:
        raise SceneError(f"{where}: unsupported camera model {name} (supported: {', '.join(SUPPORTED_MODELS)})")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    return K, dist


def load_colmap(root: Path, images_dir: str = "images") -> Scene:
    import pycolmap

    root = Path(root)
    mdir = model_dir(root)
    if mdir is None:
        raise SceneError(f"{root}: no COLMAP model (cameras.bin/.txt) in sparse/0, sparse or the folder itself")
    try:
        rec = pycolmap.Reconstruction(str(mdir))
    except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on corrupt files
        raise SceneError(f"{mdir}: cannot read COLMAP model ({exc})") from None
    img_root = root / images_dir
    if not img_root.is_dir():
        raise SceneError(f"{root}: missing image folder '{images_dir}'")
    images = sorted(rec.images.values(), key=lambda im: im.name)
    images = [im for im in images if im.has_pose]
    if not images:
        raise SceneError(f"{mdir}: the model has no registered images")
    times_path = root / "times.json"
    times = read_json(times_path) if times_path.is_file() else None
    if times_path.is_file() and not isinstance(times, dict):
        raise SceneError(f"{times_path}: expected a JSON object {{image name: time}}, got {type(times).__name__}")
    frames = []
    for k, im in enumerate(images):
        where = f"{mdir.name}/images: image {im.name!r}"
        path = inside(img_root, im.name, where)  # a name may not reach outside the image folder
        if not path.is_file():
            raise SceneError(f"{where} is not in {images_dir}/")
        if im.camera_id not in rec.cameras:
            raise SceneError(f"{where}: camera {im.camera_id} is not in the model")
        K, dist = camera_from_colmap(rec.cameras[im.camera_id], str(mdir / "cameras"))
        viewmat = np.eye(4)
        viewmat[:3] = np.asarray(im.cam_from_world().matrix() if callable(im.cam_from_world) else im.cam_from_world.matrix())
        info: dict = {"time": k / max(len(images) - 1, 1)}
        if times is not None:
            if im.name not in times:
                raise SceneError(f"{times_path}: no entry for image {im.name}")
            entry = times[im.name]
            info = entry if isinstance(entry, dict) else {"time": entry}
        entry_where = f"{times_path.name} entry {im.name!r}"
        split = info.get("split", "train")
        if split not in ("train", "test"):
            raise SceneError(f"{entry_where}: field 'split' should be train or test, got {json.dumps(split)[:40]}")
        cam = rec.cameras[im.camera_id]
        frames.append(
            Frame(
                id=Path(im.name).stem,
                image_path=path,
                time=number(info, "time", entry_where),
                camera=Camera(K=K, viewmat=viewmat, width=int(cam.width), height=int(cam.height), distortion=dist),
                exposure=number(info, "exposure", entry_where, 0.0),
                split=split,
                camera_id=number(info, "camera_id", entry_where, 0, integer=True),
            )
        )
    frames.sort(key=lambda f: (f.camera_id, f.time, f.id))
    pts = list(rec.points3D.values())
    points = np.array([p.xyz for p in pts], dtype=np.float64).reshape(-1, 3)
    colors = np.array([p.color for p in pts], dtype=np.float64).reshape(-1, 3) / 255.0
    return Scene(name=root.name, root=root, frames=frames, points=points, point_colors=colors, source_format="colmap")


def write_colmap(scene: Scene, root: Path) -> None:
    """Writes `root/sparse/0` (binary) and `root/images/`, one PINHOLE or OPENCV camera per
    distinct intrinsics, images named `ID.png` (names sort in time order per camera)."""
    import pycolmap

    from .common import copy_into

    root = Path(root)
    rec = pycolmap.Reconstruction()
    cam_ids: dict[tuple, int] = {}
    for k, f in enumerate(scene.frames, start=1):
        c = f.camera
        key = (c.width, c.height, *np.round(c.K.reshape(-1), 9), *np.round(c.distortion, 9))
        if key not in cam_ids:
            cam_ids[key] = len(cam_ids) + 1
            d = c.distortion
            if np.any(d[[4]] != 0):
                raise SceneError(f"frame {f.id}: COLMAP's OPENCV model has no k3 term")
            if np.any(d != 0):
                model, params = "OPENCV", [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], d[0], d[1], d[2], d[3]]
            else:
                model, params = "PINHOLE", [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]]
            rec.add_camera_with_trivial_rig(
                pycolmap.Camera(model=model, width=c.width, height=c.height, params=params, camera_id=cam_ids[key])
            )
        name = f"{f.id}{f.image_path.suffix}"
        image = pycolmap.Image(name=name, camera_id=cam_ids[key], image_id=k)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(c.viewmat[:3]))
        copy_into(f.image_path, root / "images" / name)
    for p, col in zip(scene.points, scene.point_colors):
        rec.add_point3D(p, pycolmap.Track(), (np.clip(col, 0, 1) * 255).round().astype(np.uint8))
    out = root / "sparse" / "0"
    out.mkdir(parents=True, exist_ok=True)
    rec.write(str(out))
    from .common import write_json

    write_json(
        root / "times.json",
        {
            f"{f.id}{f.image_path.suffix}": {"time": f.time, "camera_id": f.camera_id, "split": f.split, "exposure": f.exposure}
            for f in scene.frames
        },
    )
