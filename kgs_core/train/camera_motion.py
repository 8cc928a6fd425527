"""The training camera's own motion during each exposure, for blurring every Gaussian along its
velocity relative to the camera (`TrainConfig.camera_blur`; docs/method.md, "The camera's own blur").

A still world point `x` moves relative to the camera like a point with world velocity
`A x + b` seen by a still camera, `A = Rᵀ dR/dt` (skew-symmetric for a rigid camera: an
angular velocity `w`) and `b = Rᵀ dT/dt`, per unit of normalised time. `poses` takes them
from the central difference of the neighbouring frames' poses; hand-held shake is faster than
the frame rate, so that estimate aliases (median error 52 % at 30 frames), and `learned`
starts from it and fits `w, b` per frame to the blurry images through the blurred covariances.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..data.scene import Frame


def skew(w: Tensor) -> Tensor:
    """`(3, 3)` matrix of the cross product with `w (3,)`: `skew(w) x = w × x`."""
    zero = torch.zeros((), dtype=w.dtype, device=w.device)
    return torch.stack([torch.stack([zero, -w[2], w[1]]), torch.stack([w[2], zero, -w[0]]), torch.stack([-w[1], w[0], zero])])


def motions_from_poses(frames: list[Frame]) -> dict[str, tuple[Tensor, Tensor]]:
    """Per frame id, `camera_motion_from_poses` from its neighbours in time on the same
    physical camera (one-sided at the ends); frames alone on their camera are left out."""
    out = {}
    by_camera: dict[int, list[Frame]] = {}
    for f in frames:
        by_camera.setdefault(f.camera_id, []).append(f)
    for seq in by_camera.values():
        seq.sort(key=lambda f: f.time)
        if len(seq) < 2:
            continue
        for i, f in enumerate(seq):
            a, b = seq[max(i - 1, 0)], seq[min(i + 1, len(seq) - 1)]
            out[f.id] = camera_motion_from_poses(a.camera.viewmat, f.camera.viewmat, b.camera.viewmat, a.time, b.time)
    return out


class CameraMotion(nn.Module):
    """Per training frame `(w, b)` as one `(F, 6)` parameter, initialised from the poses;
    trainable when `learned`."""

    def __init__(self, frames: list[Frame], learned: bool):
        super().__init__()
        init = motions_from_poses(frames)
        self.index = {fid: i for i, fid in enumerate(sorted(init))}
        rows = torch.zeros(len(self.index), 6)
        for fid, i in self.index.items():
            A, b = init[fid]
            w = 0.5 * (A - A.T)  # the rotational part (a finite difference is not exactly skew)
            rows[i] = torch.cat([torch.stack([w[2, 1], w[0, 2], w[1, 0]]), b])
        self.motion = nn.Parameter(rows, requires_grad=learned)

    def get(self, frame_id: str) -> tuple[Tensor, Tensor] | None:
        """`(A (3, 3), b (3,))` of a frame, None for a frame without neighbours."""
        i = self.index.get(frame_id)
        if i is None:
            return None
        row = self.motion[i]
        return skew(row[:3]), row[3:]


def camera_motion_from_poses(prev_viewmat, viewmat, next_viewmat, t_prev: float, t_next: float) -> tuple[Tensor, Tensor]:
    """The camera's motion at a frame, from the poses of its neighbours (central difference of
    the world-to-camera matrices `(4, 4)`), as `(A, b)`: a still world point `x` moves relative
    to the camera like a point with world velocity `A x + b` seen by a still camera
    (`A = R^T dR/dt`, `b = R^T dT/dt`, per unit of normalised time)."""
    W = torch.as_tensor(viewmat, dtype=torch.float64)
    dW = torch.as_tensor(next_viewmat, dtype=torch.float64) - torch.as_tensor(prev_viewmat, dtype=torch.float64)
    dW = dW / max(t_next - t_prev, 1e-12)
    R = W[:3, :3]
    return (R.T @ dW[:3, :3]).float(), (R.T @ dW[:3, 3]).float()


def camera_motion_records(motion: CameraMotion, frames: list[Frame]) -> list[dict]:
    """What run.json keeps of a run's camera motion (`info["camera_motion"]`), in time order:
    per training frame `{"t", "w" (3,), "b" (3,)}`, so that a viewer's "as captured" render can
    show the shake the run learned (`nearest_camera_motion`)."""
    rows = []
    for f in frames:
        i = motion.index.get(f.id)
        if i is not None:
            row = motion.motion[i].detach().tolist()
            rows.append({"t": float(f.time), "w": row[:3], "b": row[3:]})
    return sorted(rows, key=lambda r: r["t"])


def nearest_camera_motion(records: list[dict] | None, t: float) -> tuple[Tensor, Tensor] | None:
    """`(A (3, 3), b (3,))` of the training frame nearest in time to `t` among
    `camera_motion_records`, None without any: the shake of the exposure a viewer at time `t`
    shows "as captured"."""
    if not records:
        return None
    near = min(records, key=lambda r: abs(float(r["t"]) - t))
    return skew(torch.tensor(near["w"], dtype=torch.float32)), torch.tensor(near["b"], dtype=torch.float32)
