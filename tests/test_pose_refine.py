"""Pose refinement of the training cameras (train/pose_refine.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from kgs_core.data.scene import Camera, Frame, Scene
from kgs_core.model.gaussians import GaussiansAt
from kgs_core.model.kinematics import so3_exp
from kgs_core.model.render import transform_gaussians
from kgs_core.render import rasterize
from kgs_core.render.covariance import covariance_from_quat_scale, pack_covariance
from kgs_core.render.random_scene import random_scene
from kgs_core.train.config import make_config
from kgs_core.train.pose_refine import PoseCorrection


def _scene_and_frame(seed: int = 0):
    sc = random_scene(300, 48, 40, overlap=20.0, seed=seed)
    cam = Camera(K=sc.K.numpy().astype(np.float64), viewmat=sc.viewmat.numpy().astype(np.float64), width=sc.width, height=sc.height)
    frame = Frame(id="f0", image_path=Path("unused.png"), time=0.0, camera=cam)
    g = GaussiansAt(
        means=sc.means,
        covars6=pack_covariance(covariance_from_quat_scale(sc.quats, sc.scales)),
        opacities=sc.opacities,
        sh=sc.colors[:, None, :],
        dynamic=torch.zeros(300, dtype=torch.bool),
    )
    return sc, frame, g


def _render(g: GaussiansAt, sc, viewmat: torch.Tensor) -> torch.Tensor:
    return rasterize(g.means, g.opacities, viewmat, sc.K, sc.width, sc.height, covars=g.covars6, colors=g.sh[:, 0, :]).image


def _corrected_viewmat(delta: torch.Tensor, viewmat: torch.Tensor) -> torch.Tensor:
    E = torch.eye(4)
    E[:3, :3] = so3_exp(delta[None, :3])[0]
    E[:3, 3] = delta[3:]
    return E @ viewmat


def test_world_transform_renders_the_corrected_camera():
    """Rendering the moved Gaussians from the recorded camera is rendering the Gaussians from
    the corrected camera `E V`."""
    sc, frame, g = _scene_and_frame()
    pc = PoseCorrection([frame])
    with torch.no_grad():
        pc.delta[0] = torch.tensor([0.02, -0.015, 0.01, 0.03, -0.02, 0.05])
    R, t = pc.world_transform(frame)
    moved = _render(transform_gaussians(g, R, t), sc, sc.viewmat)
    direct = _render(g, sc, _corrected_viewmat(pc.delta[0].detach(), sc.viewmat))
    assert (direct - _render(g, sc, sc.viewmat)).abs().max() > 0.05  # the correction changes the image
    assert torch.allclose(moved, direct, atol=2e-4)
    assert pc.world_transform(Frame(id="other", image_path=Path("x"), time=0.0, camera=frame.camera)) is None


def test_pose_correction_recovers_a_perturbed_pose():
    """Fitting the correction alone to an image taken from a perturbed camera finds the
    perturbation (the gradient reaches it through the Gaussians' means and covariances)."""
    sc, frame, g = _scene_and_frame(seed=1)
    truth = torch.tensor([0.01, -0.012, 0.006, 0.02, 0.015, -0.01])
    with torch.no_grad():
        target = _render(g, sc, _corrected_viewmat(truth, sc.viewmat))
    pc = PoseCorrection([frame])
    opt = torch.optim.Adam(pc.parameters(), lr=2e-3)
    start = float((_render(g, sc, sc.viewmat) - target).abs().mean())
    for _ in range(300):
        img = _render(transform_gaussians(g, *pc.world_transform(frame)), sc, sc.viewmat)
        loss = (img - target).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss.detach()) < 0.1 * start
    # The image pins the rotation and the in-plane translation; depth is the weakest.
    assert (pc.delta.detach()[0, :5] - truth[:5]).abs().max() < 3e-3


def test_pose_refine_is_an_option_off_by_default(tmp_path):
    cam = Camera(K=np.eye(3) * 50, viewmat=np.eye(4), width=8, height=8)
    frames = [Frame(id=f"f{i}", image_path=tmp_path / "x.png", time=i / 3, camera=cam) for i in range(4)]
    real = Scene(name="clip", root=tmp_path, frames=frames, source_format="nerfies", extras={"ingest": {}})
    assert not make_config("fast", scene=real).pose_refine
    assert make_config("fast", scene=real, pose_refine=True).pose_refine
