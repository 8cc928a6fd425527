"""The decompositions' reading of the optical flow: what moves that K has not seen move.

The decomposition (paper Sec. 3.2) calls a Gaussian dynamic when the temporal variance K of its
predicted offsets exceeds τ. At the first decomposition, 20 % into the run, the deformation field may
not yet have learned a moving object's motion: on the synthetic spinning top it arrives all at
once between 30 and 35 % of the run, so every Gaussian of the top has K under τ and is called
static. A static Gaussian renders without the field, so the field gets no gradient there again
and the object stays where it was, a ghost (the real clips' "coloured blob where it turns").

So at every decomposition the optical flow between consecutive training frames votes too. A pixel
moves on its own where the flow differs from the motion the rendered scene would make if it
stood still (`spawn.independent_motion`) by more than FLOW_VOTE_PX and by more than
FLOW_VOTE_RELATIVE of that still motion. The relative test is what makes it usable on real
footage: a hand-held pan's depth errors move the predicted still motion in proportion to it,
and at an absolute pixel the test marked several times the moving person's pixels as moving.
Of those pixels it keeps the ones that the Gaussians K already calls dynamic cover under
half, in solid regions (`spawn.large_regions`); a Gaussian that K leaves static and that sits on
such pixels in at least `share` of the sampled frames where it is visible becomes dynamic (at
a re-decomposition: stays dynamic, and on the synthetic scenes' two-way re-decompositions also turns dynamic,
where K would have turned it static: the field may learn a motion later than the first decomposition,
or never, as on the tumbling die). docs/real-footage.md, "The decompositions read the flow", has the
measurements.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..data.scene import Frame
from ..model.dynamic import KinematicsGS
from ..model.render import camera_tensors, render_model
from .flow import DEPTH_SLACK, project
from .spawn import independent_motion, large_regions

FLOW_VOTE_PX = 1.0  # the flow this far off the still scene's motion ...
FLOW_VOTE_RELATIVE = 0.5  # ... and this far in proportion to that motion: moving on its own
FLOW_VOTE_VIEWS = 16  # training frames read, spread over the clip
COVERED = 0.5  # a pixel the K-dynamic Gaussians draw this much of already has its motion
# Fewer Gaussians than this found and the reading changes nothing: a few on the edge of a region
# the K-dynamic ones cover are not an object the field missed (the demo's sheet gets 0-1; the
# spinning top 240, the real clips 0-57).
MIN_GAUSSIANS = 10


def read_frames(frames: list[Frame], views: int = FLOW_VOTE_VIEWS) -> list[Frame]:
    """The frames the reading reads: `views` of those with a later frame of the same camera (a
    flow to read), spread evenly over them in `frames`' order."""
    last = {}
    for f in frames:
        last[f.camera_id] = max(last.get(f.camera_id, f.time), f.time)
    candidates = [f for f in frames if f.time < last[f.camera_id]]
    if not candidates:
        return []
    pick = np.linspace(0, len(candidates) - 1, min(views, len(candidates))).round().astype(int)
    return [candidates[i] for i in sorted(set(int(p) for p in pick))]


@torch.no_grad()
def flow_moving(
    model: KinematicsGS,
    frames: list[Frame],
    flows: dict[str, tuple[int, Tensor]],
    by_k: Tensor,
    share: float,
    exposure: float,
    dt: float,
    world_transform=None,
    views: int = FLOW_VOTE_VIEWS,
) -> Tensor:
    """`(N,)` bool: the Gaussians K leaves static (`by_k (N,)`: what K calls dynamic) that sit on
    uncovered independent motion in at least `share` of the read frames where they are visible
    (no deeper than DEPTH_SLACK x the rendered depth at their pixel), and are visible in two or
    more; none when fewer than MIN_GAUSSIANS are. `frames`: the training frames; `flows`:
    `train.flow.frame_flows` of them (at least of `read_frames(frames, views)`); `world_transform(frame)`: a training camera's pose
    correction, or None."""
    n = len(model)
    votes, seen = torch.zeros(n), torch.zeros(n)
    cover_colour = by_k.float()[:, None]
    for f in read_frames(frames, views):
        if f.id not in flows:  # (frame_flows skips a pair whose sizes differ)
            continue
        out, g = render_model(
            model,
            f.camera,
            f.time,
            exposure,
            dt,
            colors=cover_colour,
            velocity=False,
            world_transform=world_transform(f) if world_transform else None,
        )
        viewmat, K = camera_tensors(f.camera)
        j, flow = flows[f.id]
        moving = independent_motion(
            out.depth, viewmat, K, *camera_tensors(frames[j].camera), flow, threshold=FLOW_VOTE_PX, relative=FLOW_VOTE_RELATIVE
        )
        moving = torch.as_tensor(large_regions(moving & (out.image[..., 0] < COVERED).cpu().numpy()), device=out.image.device)
        H, W = moving.shape
        uv, z = project(g.means, viewmat, K)
        u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
        inside = (z > 1e-4) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        uc, vc = u.clamp(0, W - 1), v.clamp(0, H - 1)
        d = out.depth[vc, uc, 0]
        visible = inside & (d > 0) & (z <= DEPTH_SLACK * d)
        seen += visible.float()
        votes += (visible & moving[vc, uc]).float()
    moving = ~by_k & (seen >= 2) & (votes >= share * seen)
    return moving if int(moving.sum()) >= MIN_GAUSSIANS else torch.zeros_like(moving)
