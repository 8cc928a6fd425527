"""The in-memory scene: frames, cameras, times, exposure, SfM points and optional ground truth.

Every loader (`kgs_core.data.formats`) produces a `Scene`; training, evaluation and the
server consume only this. Conventions (see docs/data.md):

* Cameras: OpenCV pinhole (x right, y down, z forward), world-to-camera `viewmat (4, 4)`,
  pixel centres at `+0.5`. Distortion coefficients are OpenCV's `(k1, k2, p1, p2, k3)`.
* Time `t` in [0, 1] over the sequence; `dt` is one frame interval in those units.
* Exposure: the fraction of the frame interval the shutter is open (0 = sharp).
* World units are normalised so cameras and points fit a unit-ish sphere; `normalization`
  records the similarity applied (`x_norm = scale * (x_orig - center)`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from .images import read_image, read_mask, read_motion


class SceneError(ValueError):
    """A dataset is missing, malformed or inconsistent; the message names the file or field."""


@dataclass(frozen=True)
class Camera:
    K: np.ndarray  # (3, 3) intrinsics
    viewmat: np.ndarray  # (4, 4) world-to-camera
    width: int
    height: int
    distortion: np.ndarray = field(default_factory=lambda: np.zeros(5))  # k1, k2, p1, p2, k3

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (pixel centres stay at +0.5)."""
        K = self.K.copy()
        K[:2] *= factor
        return replace(self, K=K, width=int(round(self.width * factor)), height=int(round(self.height * factor)))


@dataclass
class Frame:
    """One image of the sequence and everything known about it."""

    id: str
    image_path: Path
    time: float  # in [0, 1]
    camera: Camera
    exposure: float = 0.0  # fraction of the frame interval
    split: str = "train"  # "train" or "test"
    camera_id: int = 0  # physical camera: 0 = the blurry training camera, 1 = held-out
    sharp_path: Path | None = None  # ground truth: sharp image at mid-exposure
    mask_path: Path | None = None  # ground truth: dynamic pixels (sharp, mid-exposure)
    motion_path: Path | None = None  # ground truth: (H, W, 2) image motion per frame interval

    def image(self) -> np.ndarray:
        """`(H, W, 3)` float32 in [0, 1]."""
        return read_image(self.image_path)

    def sharp(self) -> np.ndarray | None:
        return read_image(self.sharp_path) if self.sharp_path else None

    def mask(self) -> np.ndarray | None:
        return read_mask(self.mask_path) if self.mask_path else None

    def motion(self) -> np.ndarray | None:
        return read_motion(self.motion_path) if self.motion_path else None


@dataclass
class Normalization:
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scale: float = 1.0

    def apply_points(self, x: np.ndarray) -> np.ndarray:
        return (x - self.center) * self.scale

    def apply_viewmat(self, viewmat: np.ndarray) -> np.ndarray:
        """World-to-camera in normalised units: `p_cam' = s * p_cam`, so `t' = s (R c + t)`."""
        out = viewmat.copy()
        R, t = viewmat[:3, :3], viewmat[:3, 3]
        out[:3, 3] = self.scale * (R @ self.center + t)
        return out

    def to_dict(self) -> dict:
        return {"center": [float(v) for v in self.center], "scale": float(self.scale)}


@dataclass
class Scene:
    name: str
    root: Path
    frames: list[Frame]
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) SfM points
    point_colors: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (P, 3) in [0, 1]
    normalization: Normalization = field(default_factory=Normalization)
    source_format: str = ""
    extras: dict = field(default_factory=dict)  # e.g. the generator's description

    def __post_init__(self) -> None:
        validate_frames(self.frames)

    @property
    def train_frames(self) -> list[Frame]:
        return [f for f in self.frames if f.split == "train"]

    @property
    def test_frames(self) -> list[Frame]:
        return [f for f in self.frames if f.split == "test"]

    @cached_property
    def dt(self) -> float:
        """One frame interval in normalised time (from the training camera's frames)."""
        times = sorted({f.time for f in self.train_frames})
        if len(times) < 2:
            return 1.0
        return float(np.median(np.diff(times)))

    @property
    def exposure(self) -> float:
        """The training frames' exposure (the largest if they differ)."""
        return max((f.exposure for f in self.train_frames), default=0.0)

    @property
    def has_ground_truth(self) -> bool:
        return any(f.sharp_path or f.mask_path for f in self.frames)

    def normalize(self) -> "Scene":
        """Re-centre and scale so cameras and points fit a unit-ish sphere (in place)."""
        centers = np.stack([f.camera.center for f in self.frames])
        if len(self.points) >= 10:
            center = np.median(self.points, axis=0)
            d_pts = np.percentile(np.linalg.norm(self.points - center, axis=1), 95)
        else:
            center = centers.mean(axis=0)
            d_pts = 0.0
        radius = max(float(np.linalg.norm(centers - center, axis=1).max()), float(d_pts), 1e-9)
        norm = Normalization(center=center, scale=1.0 / radius)
        for f in self.frames:
            f.camera = replace(f.camera, viewmat=norm.apply_viewmat(f.camera.viewmat))
        self.points = norm.apply_points(self.points)
        prev = self.normalization
        # Compose with any normalisation applied before: x'' = s2 (s1 (x - c1) - c2).
        self.normalization = Normalization(center=prev.center + center / prev.scale, scale=prev.scale * norm.scale)
        return self


def validate_frames(frames: list[Frame]) -> None:
    if not frames:
        raise SceneError("the scene has no frames")
    ids = [f.id for f in frames]
    if len(set(ids)) != len(ids):
        dup = sorted({i for i in ids if ids.count(i) > 1})[:3]
        raise SceneError(f"duplicate frame ids: {dup}")
    for f in frames:
        if not (0.0 <= f.time <= 1.0) or not np.isfinite(f.time):
            raise SceneError(f"frame {f.id}: time {f.time} outside [0, 1]")
        if not (0.0 <= f.exposure <= 1.0):
            raise SceneError(f"frame {f.id}: exposure {f.exposure} outside [0, 1]")
        if f.split not in ("train", "test"):
            raise SceneError(f"frame {f.id}: split must be 'train' or 'test', got {f.split!r}")
        cam = f.camera
        if cam.K.shape != (3, 3) or cam.viewmat.shape != (4, 4):
            raise SceneError(f"frame {f.id}: camera matrices have wrong shapes")
        if not (np.isfinite(cam.K).all() and np.isfinite(cam.viewmat).all()):
            raise SceneError(f"frame {f.id}: camera has non-finite values")
        R = cam.viewmat[:3, :3]
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise SceneError(f"frame {f.id}: camera rotation is not a rotation matrix")
    # Time must not go backwards along the frame order within each physical camera.
    for cam_id in sorted({f.camera_id for f in frames}):
        seq = [f for f in frames if f.camera_id == cam_id]
        for a, b in zip(seq, seq[1:]):
            if b.time < a.time:
                raise SceneError(f"camera {cam_id}: time goes backwards at frame {b.id} ({a.time} after {a.id} -> {b.time})")
