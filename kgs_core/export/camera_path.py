"""Camera paths for video export: the training cameras, an orbit, one fixed view, or JSON keyframes.

Keyframe file (`--camera-path path.json`):

```json
{"width": 640, "height": 360, "fov_deg": 60, "frames": 90,
 "keyframes": [{"time": 0.0, "eye": [0, -3, 1], "target": [0, 0, 0], "up": [0, 0, 1]},
               {"time": 1.0, "eye": [3, 0, 1], "target": [0, 0, 0], "up": [0, 0, 1]}]}
```

`up` is the world direction shown up in the image; eye, target, up and time are interpolated
linearly between keyframes (`frames` images in all, evenly spaced along the keyframes).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data.scene import Camera, Frame
from ..render.camera import intrinsics, look_at


@dataclass
class PathStep:
    camera: Camera
    time: float
    frame: Frame | None = None  # the input frame this step reproduces (training path)


def training_path(frames: list[Frame], times: list[float] | None = None) -> list[PathStep]:
    """The training camera at each training frame's time; with `times`, the camera of the
    frame nearest in time to each requested time."""
    frames = sorted(frames, key=lambda f: f.time)
    if not frames:
        raise ValueError("camera path 'training': the scene has no training frames")
    if times is None:
        return [PathStep(f.camera, f.time, f) for f in frames]
    ft = np.array([f.time for f in frames])
    return [PathStep(frames[int(np.abs(ft - t).argmin())].camera, t, frames[int(np.abs(ft - t).argmin())]) for t in times]


def orbit_path(frames: list[Frame], centre: np.ndarray, times: list[float], turns: float = 1.0) -> list[PathStep]:
    """A circle around `centre` at the training cameras' mean distance and height, about their
    mean up direction, one full turn over the times (intrinsics of the first training camera)."""
    if not frames:
        raise ValueError("camera path 'orbit': the scene has no training cameras to size the orbit")
    cams = [f.camera for f in frames]
    eyes = np.stack([c.center for c in cams])
    up = np.mean([c.viewmat[:3, :3].T @ np.array([0.0, -1.0, 0.0]) for c in cams], axis=0)
    up /= max(np.linalg.norm(up), 1e-12)
    rel = eyes - centre
    height = float(np.mean(rel @ up))
    radial = rel - np.outer(rel @ up, up)
    radius = float(np.mean(np.linalg.norm(radial, axis=1)))
    e1 = radial[0] / max(np.linalg.norm(radial[0]), 1e-12)
    e2 = np.cross(up, e1)
    ref = cams[0]
    steps = []
    n = len(times)
    for i, t in enumerate(times):
        a = 2 * np.pi * turns * i / max(n, 1)
        eye = centre + height * up + radius * (np.cos(a) * e1 + np.sin(a) * e2)
        vm = look_at(eye, centre, up=up, dtype=torch.float64).numpy()
        steps.append(PathStep(Camera(K=ref.K.copy(), viewmat=vm, width=ref.width, height=ref.height), float(t)))
    return steps


def keyframe_path(path: str | Path) -> list[PathStep]:
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"camera path file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: invalid JSON ({exc.msg})") from None
    try:
        width, height = int(spec["width"]), int(spec["height"])
        fov = float(spec.get("fov_deg", 60.0))
        n = int(spec.get("frames", 60))
        keys = spec["keyframes"]
        kt = np.array([float(k["time"]) for k in keys])
        eyes = np.array([k["eye"] for k in keys], dtype=np.float64)
        targets = np.array([k["target"] for k in keys], dtype=np.float64)
        ups = np.array([k.get("up", [0.0, 0.0, 1.0]) for k in keys], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: expected width, height, keyframes[{{time, eye, target, up}}] ({exc})") from None
    if not (16 <= width <= 8192 and 16 <= height <= 8192):
        raise ValueError(f"{path}: width/height must be in 16..8192")
    if len(keys) < 1 or eyes.shape != (len(keys), 3) or targets.shape != eyes.shape or ups.shape != eyes.shape:
        raise ValueError(f"{path}: keyframes need eye, target and up as 3 numbers each")
    if not (0 < fov < 180) or n < 1 or n > 100000:
        raise ValueError(f"{path}: fov_deg must be in (0, 180) and frames in 1..100000")
    if np.any((kt < 0) | (kt > 1)):
        raise ValueError(f"{path}: keyframe times must lie in [0, 1]")
    K = intrinsics(width, height, fov).double().numpy()
    s = np.linspace(0, len(keys) - 1, n)
    steps = []
    for u in s:
        i = min(int(np.floor(u)), len(keys) - 2) if len(keys) > 1 else 0
        w = u - i if len(keys) > 1 else 0.0
        j = min(i + 1, len(keys) - 1)
        eye = (1 - w) * eyes[i] + w * eyes[j]
        target = (1 - w) * targets[i] + w * targets[j]
        up = (1 - w) * ups[i] + w * ups[j]
        vm = look_at(eye, target, up=up, dtype=torch.float64).numpy()
        steps.append(PathStep(Camera(K=K, viewmat=vm, width=width, height=height), float((1 - w) * kt[i] + w * kt[j])))
    return steps


def view_path(view: dict, times: list[float]) -> list[PathStep]:
    """One fixed camera over `times`: `view` is `{"viewmat": 4x4 world-to-camera, "fov_deg":
    horizontal field of view, "width", "height"}` (the viewer's current view)."""
    try:
        vm = np.asarray(view["viewmat"], dtype=np.float64)
        width, height, fov = int(view["width"]), int(view["height"]), float(view["fov_deg"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"view: expected viewmat, fov_deg, width and height ({exc})") from None
    if vm.shape != (4, 4) or not np.isfinite(vm).all():
        raise ValueError("view.viewmat must be a finite 4x4 matrix")
    R = vm[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise ValueError("view.viewmat's rotation is not a rotation")
    if not (16 <= width <= 4096 and 16 <= height <= 4096) or not (1 <= fov < 179):
        raise ValueError("view: width and height must be in 16..4096 and fov_deg in [1, 179)")
    K = intrinsics(width, height, fov).double().numpy()
    return [PathStep(Camera(K=K, viewmat=vm, width=width, height=height), float(t)) for t in times]
