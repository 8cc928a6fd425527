"""Per-frame corrections of the training cameras' estimated poses (`TrainConfig.pose_refine`).

Poses that structure-from-motion recovers from blurry frames are off by a fraction of a
degree, differently in every frame. A model trained against them has to explain the
misalignment, and the deformation field does: on real footage the still background moved as
a per-frame rigid shift and was called "dynamic" (docs/real-footage.md). Each training frame
gets a small rigid correction `E = [exp(w) | u]` applied in its camera frame, `V' = E V`,
fitted with the model.

The rasteriser has no gradient with respect to the view matrix, so the correction is applied
to the Gaussians instead: rendering `x` through `E V` is rendering `M x` through `V`, with
`M = V⁻¹ E V` (`world_transform`), and the rasteriser differentiates means and covariances.
The held-out cameras are not corrected: they are what the model is scored from.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ..data.scene import Frame
from ..model.kinematics import so3_exp


class PoseCorrection(nn.Module):
    """`(F, 6)` corrections `(w, u)` (rotation vector, translation in normalised scene units,
    both in the camera frame), one row per training frame, starting at zero."""

    def __init__(self, frames: list[Frame]):
        super().__init__()
        self.index = {f.id: i for i, f in enumerate(sorted(frames, key=lambda f: str(f.id)))}
        self.delta = nn.Parameter(torch.zeros(len(self.index), 6))

    def world_transform(self, frame: Frame) -> tuple[Tensor, Tensor] | None:
        """`(R (3, 3), t (3,))` such that rendering `R x + t` from the frame's recorded camera
        is rendering `x` from its corrected one; None for a frame that is not a training frame."""
        i = self.index.get(frame.id)
        if i is None:
            return None
        V = torch.as_tensor(frame.camera.viewmat, dtype=torch.float32)
        Rv, tv = V[:3, :3], V[:3, 3]
        Re = so3_exp(self.delta[i, None, :3])[0]
        return Rv.T @ Re @ Rv, Rv.T @ (Re @ tv + self.delta[i, 3:] - tv)

    @torch.no_grad()
    def summary(self) -> dict:
        """Median and largest correction over the frames: rotation in degrees, translation in
        normalised scene units (run.json's `pose_refine`)."""
        d = self.delta.detach()
        if not len(d):
            return {}
        deg = torch.rad2deg(d[:, :3].norm(dim=1))
        tr = d[:, 3:].norm(dim=1)
        return {
            "frames": len(d),
            "rotation_deg_median": float(deg.median()),
            "rotation_deg_max": float(deg.max()),
            "translation_median": float(tr.median()),
            "translation_max": float(tr.max()),
        }
