"""The viewer's controller: keeps the splat sets in step with the state (time, τ, LoD,
exposure) and the camera (orbit or fly). No GL, no imgui: the window and the tests both drive it."""

from __future__ import annotations

import math

import numpy as np
import torch

from kgs_core.render.camera import look_at
from kgs_core.train.camera_motion import nearest_camera_motion

from .state import ViewerState


class ViewerModel:
    def __init__(self, source, width: int = 960, height: int = 640):
        self.source = source
        m = source.meta
        self.state = ViewerState(tau=float(m["tau"]))
        self.width, self.height = width, height
        self.static = None
        self.dynamic = None
        self._loaded = {}  # what the current sets were fetched for
        self.frames = [f for f in source.frames if f["split"] == "train"] or source.frames
        self.reset_camera()

    # ------------------------------------------------------------ camera

    def reset_camera(self) -> None:
        """Orbit around the point the first training camera looks at, from where it stands."""
        if self.frames:
            f = self.frames[0]
            vm = np.array(f["viewmat"], dtype=np.float64)
            fov = 2 * math.atan(f["width"] / (2 * f["K"][0][0]))
        else:
            vm, fov = look_at((0.0, -3.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), dtype=torch.float64).numpy(), math.radians(60)
        R, t = vm[:3, :3], vm[:3, 3]
        eye = -R.T @ t
        self.up = -R[1]  # image up in world coordinates
        dist = max(np.linalg.norm(eye), 1e-3)
        self.target = eye + dist * R[2]
        self.distance = dist
        rel = eye - self.target
        e1, e2 = self._basis()
        self.yaw = math.atan2(rel @ e2, rel @ e1)
        self.pitch = math.asin(np.clip(rel @ self.up / dist, -1, 1))
        self.fov = fov
        self.state.viewmat = vm
        self.update_camera()

    def _basis(self):
        u = self.up
        a = np.array([1.0, 0, 0]) if abs(u[0]) < 0.9 else np.array([0, 1.0, 0])
        e1 = np.cross(np.cross(u, a), u)
        e1 /= np.linalg.norm(e1)
        return e1, np.cross(u, e1)

    def update_camera(self) -> None:
        s = self.state
        fx = 0.5 * self.width / math.tan(self.fov / 2)
        s.K = np.array([[fx, 0, self.width / 2], [0, fx, self.height / 2], [0, 0, 1]])
        if s.mode == "orbit":
            e1, e2 = self._basis()
            d = math.cos(self.pitch) * (math.cos(self.yaw) * e1 + math.sin(self.yaw) * e2) + math.sin(self.pitch) * self.up
            eye = self.target + self.distance * d
            s.viewmat = look_at(eye, self.target, self.up, dtype=torch.float64).numpy()

    def orbit(self, dyaw: float, dpitch: float) -> None:
        self.yaw += dyaw
        self.pitch = float(np.clip(self.pitch + dpitch, -1.5, 1.5))
        self.update_camera()

    def zoom(self, factor: float) -> None:
        self.distance = max(1e-3, self.distance * factor)
        self.update_camera()

    def fly(self, forward: float, right: float, upward: float) -> None:
        inv = np.linalg.inv(self.state.viewmat)
        inv[:3, 3] += forward * inv[:3, 2] + right * inv[:3, 0] - upward * inv[:3, 1]
        self.state.viewmat = np.linalg.inv(inv)

    def use_frame_camera(self, index: int) -> None:
        f = self.source.frames[index]
        self.state.mode = "fly"
        self.state.viewmat = np.array(f["viewmat"], dtype=np.float64)
        self.width, self.height = f["width"], f["height"]
        self.state.K = np.array(f["K"], dtype=np.float64)

    def nearest_frame(self) -> dict | None:
        if not self.frames:
            return None
        return min(self.frames, key=lambda f: abs(f["time"] - self.state.t))

    def shake(self) -> np.ndarray | None:
        """ "As captured": the camera's shake learned at the training frame nearest in time, as the
        static splats' sweep `A x + b` over the exposure (`(4, 3)`: A's rows, then b); None when
        sharp or when the run kept none (the dynamic set arrives blurred)."""
        s = self.state
        motion = nearest_camera_motion(self.source.meta.get("camera_motion"), s.t) if s.exposure_captured else None
        if motion is None:
            return None
        k = float(self.source.meta["dt"]) * float(self.source.meta["exposure"])
        return np.vstack([motion[0].numpy(), motion[1].numpy()[None]]) * k

    # ------------------------------------------------------------ data

    def advance(self, seconds: float) -> None:
        s = self.state
        if s.playing:
            duration = max(len(self.frames), 1) / 30.0
            s.t = (s.t + seconds * s.speed / duration) % 1.0

    def sync(self) -> bool:
        """Fetches the sets the state asks for; True when something new was loaded."""
        s = self.state
        exposure = float(self.source.meta["exposure"]) if s.exposure_captured else 0.0
        changed = False
        if abs(s.tau - float(self.source.meta["tau"])) > 1e-15 * max(s.tau, 1e-30):
            self.source.set_tau(s.tau)
            self._loaded = {}
        if self._loaded.get("static") != (s.lod, self.source.meta["tau"]):
            self.static = self.source.static(s.lod)
            self._loaded = {"static": (s.lod, self.source.meta["tau"])}
            changed = True
        key = (s.lod, self.source.meta["tau"], round(s.t, 6), exposure)
        if self._loaded.get("dynamic") != key:
            self.dynamic = self.source.dynamic(s.t, exposure, s.lod)
            self._loaded["dynamic"] = key
            changed = True
        return changed
