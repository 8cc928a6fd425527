"""Dynamic Gaussians spawned where a training frame stays unexplained (`spawn_frames`, 0: off).

The photometric loss moves a Gaussian only while its splat overlaps the pixels it should
explain. When the Gaussians that followed a moving object drift off it (docs/real-footage.md,
"Spawned Gaussians"), nothing brings them back: the static
background fills those pixels, and 3DGS densification, which clones Gaussians with large
position gradients, has nothing there to clone. This step adds what is missing where it is
missing: in the training frames that fit worst, at pixels the render still gets wrong where the
optical flow shows something moving on its own, new dynamic Gaussians in front of the
background, coloured from the frame, on those pixels at that frame's time, moving on their own
straight line through it as the flow there says (`KinematicsGS.own_velocity`), and present only
around that time (`KinematicsGS.lifespan`).

Two rules keep the new Gaussians from bending the background through the shared deformation
field: each joins a parent that moves as the flow at its pixel says (not merely the nearest
dynamic Gaussian, which on real footage is often a wall that K calls dynamic), and its loss does
not train the field (`KinematicsGS._spawned_offsets`): present for a frame, only its own
parameters learn. With neither, real-clip runs smeared a wall; with the parent rule alone, a
sign; with both, nothing. On for video ingests (`fitting.VIDEO_SPAWN_FRAMES`; docs/real-footage.md,
"Spawned Gaussians").

A moving pixel that no dynamic Gaussian follows (an object the model has lost everywhere, so
nothing moves like it) still gets a Gaussian when the spawned ones move on their own line (the
default): there the field never learns from it, so the parent rule has nothing to protect, and
what it lacks is only a depth, which it takes from the render, just in front of the background
there. Under `spawned_motion="field"` such a pixel gets none: a Gaussian the field carries
needs a parent to be carried with.
"""

from __future__ import annotations

from dataclasses import dataclass

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
BORDER_PX = 4  # the relative test of `independent_motion` reads no pixel whose still motion ends this near the border
MOTION_REACH_PX = 8  # an unexplained pixel counts as moving within this distance of independent motion
SAMPLE_STRIDE = 2  # one new Gaussian per 2x2 pixels of an unexplained region
# A parent moves like a pixel when its own image motion to the next frame is nearer the pixel's
# flow than PARENT_MATCH x the distance between that flow and the motion the parent would make
# standing still: its motion explains most of the pixel's independent motion.
PARENT_MATCH = 0.5
IN_FRONT = 0.95  # a new Gaussian's depth is at most this x the rendered background's at its pixel


@dataclass
class Spawned:
    """What `spawn_unexplained` added: `gaussians` in all, of which `without_parent` sit at the
    rendered depth because no dynamic Gaussian moves like their pixel."""

    gaussians: int = 0
    without_parent: int = 0


@dataclass
class NextFrame:
    """What the next training frame of the same camera says about motion: its camera
    (`viewmat`, `K`), the optical flow to it (`flow` (H, W, 2) px, NaN where unreliable), the
    Gaussians' positions at its time (`means` (N, 3), read for the dynamic ones) and the time
    itself (normalised)."""

    viewmat: Tensor
    K: Tensor
    flow: Tensor
    means: Tensor
    time: float


def independent_motion(
    depth: Tensor,
    viewmat: Tensor,
    K: Tensor,
    next_viewmat: Tensor,
    next_K: Tensor,
    flow: Tensor,
    threshold: float = INDEPENDENT_MOTION_PX,
    relative: float = 0.0,
) -> np.ndarray:
    """`(H, W)` bool: pixels whose optical flow to the next frame (`flow` (H, W, 2), NaN where
    unreliable) differs by more than `threshold` pixels from the motion the rendered scene
    (`depth` (H, W, 1), 0 where nothing was drawn) would make if it stood still: something moves
    there on its own. With `relative` > 0, also by more than that fraction of the still motion,
    and only where the still motion keeps the pixel BORDER_PX inside the next frame (the
    splits' reading, train/flow_vote.py). Where the flow is NaN or nothing was drawn, False."""
    H, W = depth.shape[:2]
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    z = depth[..., 0]
    world = unproject(torch.stack([u, v], -1).reshape(-1, 2), z.reshape(-1), viewmat, K)
    uv_next, _ = project(world, next_viewmat, next_K)
    still = uv_next.reshape(H, W, 2) - torch.stack([u, v], -1)
    diff = (flow - still).norm(dim=-1)
    moving = (z > 0) & torch.isfinite(diff) & (diff > threshold)
    if relative > 0:
        # A depth error moves the still scene's predicted motion in proportion to that motion
        # (a hand-held pan's near surfaces move furthest), and pixels that leave the next frame
        # have no true flow: count neither.
        nxt = uv_next.reshape(H, W, 2)
        inside = (nxt[..., 0] >= BORDER_PX) & (nxt[..., 0] < W - BORDER_PX) & (nxt[..., 1] >= BORDER_PX) & (nxt[..., 1] < H - BORDER_PX)
        moving &= inside & (diff > relative * still.norm(dim=-1))
    return moving.cpu().numpy()


def unexplained_pixels(image: Tensor, target: Tensor) -> np.ndarray:
    """`(H, W)` bool: where the render is off by more than ERROR_THRESHOLD, opened by 3x3 so that
    thin edges (a textured edge a pixel off) are not counted, in regions of MIN_REGION_PX or more."""
    err = (image.detach() - target).abs().mean(-1).cpu().numpy()
    return large_regions(err > ERROR_THRESHOLD)


def large_regions(mask: np.ndarray) -> np.ndarray:
    """`(H, W)` bool: `mask` opened by 3x3, in regions of MIN_REGION_PX or more."""
    mask = ndimage.binary_opening(mask, structure=np.ones((3, 3), bool))
    labels, n = ndimage.label(mask)
    if n == 0:
        return mask
    sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
    return np.isin(labels, 1 + np.nonzero(sizes >= MIN_REGION_PX)[0])


@torch.no_grad()
def spawn_unexplained(
    model: KinematicsGS,
    optimizer,
    state: dict,
    t: float,
    viewmat: Tensor,
    K: Tensor,
    image: Tensor,
    depth: Tensor,
    target: Tensor,
    means: Tensor,
    max_new: int,
    life: float,
    rng: np.random.Generator,
    nxt: NextFrame | None = None,
) -> Spawned:
    """Adds up to `max_new` dynamic Gaussians at the unexplained pixels of one training frame
    (`image`, `depth` (H, W, 1): its render at time `t`; `target`: the frame; `viewmat`, `K`:
    its camera; `means` (N, 3): every Gaussian's position at `t`, used for the dynamic ones;
    `life`: their presence's width in time, `KinematicsGS.lifespan`; `nxt`: the next frame of
    the camera, None where there is none). Returns what was added (`Spawned`).

    With `nxt`, only pixels where something moves on its own (`independent_motion`, within
    MOTION_REACH_PX) get Gaussians, and each copies the nearest dynamic Gaussian on screen whose
    own image motion matches the flow there (PARENT_MATCH). Under "field" the parent matters
    beyond its looks: the new Gaussian takes its K and fine-residual features and sits beside it
    in canonical space, so the deformation field learns the new Gaussian's motion in the
    parent's neighbourhood, and a parent on the background ("dynamic" by a small K) would have
    the field bend the background there; so a pixel without such a parent gets none. Under
    "own" it gets one anyway, at IN_FRONT x the rendered depth (its nominal parent, for the
    per-Gaussian state it copies, the nearest dynamic Gaussian on screen). Without `nxt`, every
    unexplained pixel counts and the parent is the nearest dynamic Gaussian on screen.

    Each new Gaussian takes the frame's colour, sits at the median depth of its region's parents
    (never behind the rendered background), and is sized to its pixel spacing. Under the model's
    `spawned_motion="own"` it sits at its pixel at `t` and its own velocity carries it, at its
    depth, to where the flow moves its pixel by the next frame (none without `nxt`); under
    "field" its canonical position is its place at `t` minus its parent's offset there, so that
    at `t` it lands near its pixel."""
    mask = unexplained_pixels(image, target)
    moving = None
    if nxt is not None:  # only what moves on its own: not a background the model has yet to fit
        moving = independent_motion(depth, viewmat, K, nxt.viewmat, nxt.K, nxt.flow)
        mask &= ndimage.binary_dilation(moving, iterations=MOTION_REACH_PX)
    dyn = torch.nonzero(model.dynamic).squeeze(1)
    if mask.sum() < MIN_REGION_PX or len(dyn) == 0:
        return Spawned()
    H, W = mask.shape
    ys, xs = np.nonzero(mask[::SAMPLE_STRIDE, ::SAMPLE_STRIDE])
    ys, xs = ys * SAMPLE_STRIDE, xs * SAMPLE_STRIDE
    if len(ys) > max_new:
        pick = rng.choice(len(ys), max_new, replace=False)
        ys, xs = ys[pick], xs[pick]
    # The dynamic Gaussians on screen, in front of the camera.
    uv, z = project(means[dyn], viewmat, K)
    on = (z > 1e-4) & (uv[:, 0] >= 0) & (uv[:, 0] <= W - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
    if not on.any():
        return Spawned()
    dyn, uv, z = dyn[on], uv[on], z[on]
    pixels = torch.tensor(np.stack([xs, ys], -1), dtype=torch.float32)
    d2 = ((pixels[:, None] - uv[None]) ** 2).sum(-1)
    orphan = torch.zeros(len(ys), dtype=torch.bool)
    f = None
    if nxt is not None:
        # Each pixel's flow is that of the nearest pixel moving on its own (the unexplained
        # pixels of a blurred object often fail the flow's forward-backward check themselves).
        _, (iy, ix) = ndimage.distance_transform_edt(~moving, return_indices=True)
        f = nxt.flow[torch.as_tensor(iy[ys, xs], device=nxt.flow.device), torch.as_tensor(ix[ys, xs], device=nxt.flow.device)]  # (M, 2)
        own = project(nxt.means[dyn], nxt.viewmat, nxt.K)[0] - uv  # (D, 2): each candidate's motion
        still = project(means[dyn], nxt.viewmat, nxt.K)[0] - uv  # the same, had it stood still
        matches = (own[None] - f[:, None]).norm(dim=-1) < PARENT_MATCH * (still[None] - f[:, None]).norm(dim=-1)
        orphan = ~matches.any(1)
        # An orphan's nominal parent is the nearest on screen, whatever its motion.
        d2 = torch.where(matches | orphan[:, None], d2, torch.inf)
        # Orphans need a depth from the render, and a line of their own to move on.
        keep = ~orphan | (depth[ys, xs, 0] > 0) if model.config.spawned_motion == "own" else ~orphan
        if not keep.any():
            return Spawned()
        keep_np = keep.cpu().numpy()
        pixels, d2, ys, xs, f, orphan = pixels[keep], d2[keep], ys[keep_np], xs[keep_np], f[keep], orphan[keep]
    nearest = d2.argmin(1)
    parents = dyn[nearest]
    # Depth: the region's parents' (the object the new Gaussians join), or the render's for an
    # orphan; never behind the rendered background.
    bg = depth[ys, xs, 0].cpu().numpy()
    z_new = float(torch.median(z[nearest[~orphan]])) if (~orphan).any() else 0.0
    z_pix = np.where(bg > 0, np.minimum(z_new, IN_FRONT * bg), z_new)
    z_pix = np.where(orphan.cpu().numpy(), IN_FRONT * bg, z_pix)
    z_pix = torch.tensor(z_pix, dtype=torch.float32)
    world = unproject(pixels, z_pix, viewmat, K)
    p = model.params
    m = len(parents)
    scale = torch.log(0.6 * SAMPLE_STRIDE * z_pix / float(K[0, 0]))[:, None].repeat(1, 3)
    quats = torch.zeros(m, 4)
    quats[:, 0] = 1
    new = GaussianParams(
        means=world,
        quats=quats,
        log_scales=scale,
        opacity_logits=torch.zeros(m),
        sh0=rgb_to_sh0(target[ys, xs].clamp(0, 1).float())[:, None, :],
        sh_rest=torch.zeros(m, *p.sh_rest.shape[1:]),
        features=p.features.detach()[parents].clone(),
    )
    lifespan = torch.tensor([t, life]).repeat(m, 1)
    if model.config.spawned_motion == "own":
        # The flow moves the pixel to `pixels + f` by the next frame: the point at the same
        # camera depth there, reached at the next frame's time.
        velocity = torch.zeros(m, 3)
        if nxt is not None and nxt.time != t:
            velocity = (unproject(pixels + f, z_pix, nxt.viewmat, nxt.K) - world) / (nxt.time - t)
        model.add_gaussians(new, parents, optimizer, state, lifespan=lifespan, own_velocity=velocity)
        return Spawned(m, int(orphan.sum()))
    n0 = len(model)
    model.add_gaussians(new, parents, optimizer, state, lifespan=lifespan)
    # Canonical position: the parent's, moved as far as the new Gaussian sits from the parent at
    # t. Its coarse-to-fine neighbours and fine-residual features are then the parent's, so the
    # deformation moves it with the parent, and at t it lands on its pixel (up to how much the
    # field varies between the two).
    shift = means[parents] - p.means.detach()[parents]
    canonical = model.params.means.detach().clone()
    canonical[n0:] = world - shift
    model.params = set_param(model.params, optimizer, "means", canonical)
    return Spawned(m)
