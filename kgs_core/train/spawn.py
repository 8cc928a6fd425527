"""Dynamic Gaussians spawned where a training frame stays unexplained (`spawn_frames`, 0: off).

The photometric loss moves a Gaussian only while its splat overlaps the pixels it should
explain. When the Gaussians that followed a moving object drift off it (on walk, the person in
the last quarter of the clip, docs/real-footage.md), nothing brings them back: the static
background fills those pixels, and 3DGS densification, which clones Gaussians with large
position gradients, has nothing there to clone. This step adds what is missing where it is
missing: in the training frames that fit worst, at pixels the render still gets wrong where the
optical flow shows something moving on its own, new dynamic Gaussians in front of the
background, coloured from the frame, placed so that at that frame's time the deformation puts
them on those pixels, and present only around that time (`KinematicsGS.lifespan`).

An option, off by default: on walk it brings the lost person back, but in one run of five it
also warped the background through the field (docs/real-footage.md, "Spawned Gaussians").
"""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from ..model.dynamic import KinematicsGS
from ..model.gaussians import GaussianParams, set_param
from ..render.sh import rgb_to_sh0
from .flow import project, unproject

ERROR_THRESHOLD = 0.15  # mean absolute colour error (0-1) that counts as unexplained
MIN_REGION_PX = 30  # smaller unexplained regions (after the opening) are left to the loss
SPAWN_LOSS_RATIO = 1.5  # a frame gets new Gaussians when its running loss is this x the median frame's
INDEPENDENT_MOTION_PX = 1.0  # flow this far from the still scene's motion: something moves on its own
MOTION_REACH_PX = 8  # an unexplained pixel counts as moving within this distance of independent motion
SAMPLE_STRIDE = 2  # one new Gaussian per 2x2 pixels of an unexplained region


def independent_motion(depth: Tensor, viewmat: Tensor, K: Tensor, next_viewmat: Tensor, next_K: Tensor,
                       flow: Tensor) -> np.ndarray:
    """`(H, W)` bool: pixels whose optical flow to the next frame (`flow` (H, W, 2), NaN where
    unreliable) differs by more than INDEPENDENT_MOTION_PX from the motion the rendered scene
    (`depth` (H, W, 1), 0 where nothing was drawn) would make if it stood still: something moves
    there on its own. Where the flow is NaN or nothing was drawn, False."""
    H, W = depth.shape[:2]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    z = depth[..., 0]
    world = unproject(torch.stack([u, v], -1).reshape(-1, 2), z.reshape(-1), viewmat, K)
    uv_next, _ = project(world, next_viewmat, next_K)
    still = uv_next.reshape(H, W, 2) - torch.stack([u, v], -1)
    diff = (flow - still).norm(dim=-1)
    return ((z > 0) & torch.isfinite(diff) & (diff > INDEPENDENT_MOTION_PX)).numpy()


def unexplained_pixels(image: Tensor, target: Tensor) -> np.ndarray:
    """`(H, W)` bool: where the render is off by more than ERROR_THRESHOLD, opened by 3x3 so that
    thin edges (a textured edge a pixel off) are not counted, in regions of MIN_REGION_PX or more."""
    err = (image.detach() - target).abs().mean(-1).numpy()
    mask = ndimage.binary_opening(err > ERROR_THRESHOLD, structure=np.ones((3, 3), bool))
    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
    return np.isin(labels, 1 + np.nonzero(sizes >= MIN_REGION_PX)[0])


@torch.no_grad()
def spawn_unexplained(model: KinematicsGS, optimizer, state: dict, t: float, viewmat: Tensor, K: Tensor,
                      image: Tensor, depth: Tensor, target: Tensor, dynamic_means: Tensor, max_new: int,
                      life: float, rng: np.random.Generator, moving: np.ndarray | None = None) -> int:
    """Adds up to `max_new` dynamic Gaussians at the unexplained pixels of one training frame
    (`image`, `depth` (H, W, 1): its render at time `t`; `target`: the frame; `viewmat`, `K`:
    its camera; `dynamic_means` (N, 3): every Gaussian's position at `t`, used for the dynamic
    ones; `life`: their presence's width in time, `KinematicsGS.lifespan`; `moving` (H, W): where
    the frame moves on its own, `independent_motion`, None: everywhere). Returns how many were
    added.

    Each new Gaussian copies the nearest dynamic Gaussian on screen (its flag, K and fine-residual
    features: it joins that object's motion), takes the frame's colour, sits at the median depth
    of the dynamic Gaussians drawn over the region (in front of the background the render shows
    there), and is sized to its pixel spacing. Its canonical position is its place at `t` minus
    its parent's offset there, so that at `t` it lands near its pixel."""
    mask = unexplained_pixels(image, target)
    if moving is not None:  # only what moves on its own: not a background the model has yet to fit
        mask &= ndimage.binary_dilation(moving, iterations=MOTION_REACH_PX)
    dyn = torch.nonzero(model.dynamic).squeeze(1)
    if mask.sum() < MIN_REGION_PX or len(dyn) == 0:
        return 0
    H, W = mask.shape
    ys, xs = np.nonzero(mask[::SAMPLE_STRIDE, ::SAMPLE_STRIDE])
    ys, xs = ys * SAMPLE_STRIDE, xs * SAMPLE_STRIDE
    if len(ys) > max_new:
        pick = rng.choice(len(ys), max_new, replace=False)
        ys, xs = ys[pick], xs[pick]
    # The dynamic Gaussians on screen, in front of the camera.
    cam = dynamic_means[dyn] @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    front = z > 1e-4
    uv = (cam @ K.T)[:, :2] / z.clamp_min(1e-6)[:, None]
    on = front & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    if not on.any():
        return 0
    dyn, uv, z = dyn[on], uv[on], z[on]
    # Depth: the dynamic Gaussians drawn over the region (dilated), else every one on screen;
    # never behind the rendered background.
    near = ndimage.binary_dilation(mask, iterations=8)
    px = uv.round().long()
    over = torch.from_numpy(near)[px[:, 1], px[:, 0]]
    z_new = float(torch.median(z[over] if over.any() else z))
    bg = depth[ys, xs, 0].numpy()
    z_pix = np.where(bg > 0, np.minimum(z_new, 0.95 * bg), z_new)
    pixels = torch.tensor(np.stack([xs, ys], -1), dtype=torch.float32)
    world = unproject(pixels, torch.tensor(z_pix, dtype=torch.float32), viewmat, K)
    # Parent: the nearest dynamic Gaussian on screen.
    d2 = ((pixels[:, None] - uv[None]) ** 2).sum(-1)
    parents = dyn[d2.argmin(1)]
    p = model.params
    m = len(parents)
    scale = torch.tensor(np.log(0.6 * SAMPLE_STRIDE * z_pix / float(K[0, 0])), dtype=torch.float32)[:, None].repeat(1, 3)
    quats = torch.zeros(m, 4)
    quats[:, 0] = 1
    new = GaussianParams(
        means=world, quats=quats, log_scales=scale, opacity_logits=torch.zeros(m),
        sh0=rgb_to_sh0(target[ys, xs].clamp(0, 1).float())[:, None, :],
        sh_rest=torch.zeros(m, *p.sh_rest.shape[1:]), features=p.features.detach()[parents].clone())
    n0 = len(model)
    model.add_gaussians(new, parents, optimizer, state, lifespan=torch.tensor([t, life]).repeat(m, 1))
    # Canonical position: the parent's, moved as far as the new Gaussian sits from the parent at
    # t. Its coarse-to-fine neighbours and fine-residual features are then the parent's, so the
    # deformation moves it with the parent, and at t it lands on its pixel (up to how much the
    # field varies between the two).
    shift = (dynamic_means[parents] - p.means.detach()[parents])
    means = model.params.means.detach().clone()
    means[n0:] = world - shift
    model.params = set_param(model.params, optimizer, "means", means)
    return m
