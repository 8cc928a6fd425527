"""Optical-flow supervision of the deforming Gaussians' image motion (`lambda_flow`, 0: off).

The photometric loss moves a Gaussian only while its splat overlaps the pixels it should
explain: a moving object the field has lost track of gets no gradient back (docs/real-footage.md,
"Moving objects lost in part of the clip"). Optical flow between consecutive training frames of
one camera says where each pixel goes, whether or not the render is there yet. The term asks
each deforming Gaussian that is visible at the frame's time (in front of the rendered depth at its
pixel) to move, between this frame's time and the next frame's, as the flow at its pixel says.
Flow is classical (OpenCV, computed once per run): nothing to download. By default it is DIS
(medium preset), smooth on large surfaces. DIS stops at half resolution and matches 8 px
patches, so it gives a small object the motion around it (a 16 px patch moving 3 px over a
background moving 1 px the other way: 2.2-2.4 px). The options (`flow_method` for the flow term
and spawning, `flow_vote_method` for the decompositions' reading) are "dis_full", DIS down to full
resolution, and "fused", DIS and Farneback (5 px windows) per pixel, whichever warps the next
frame closer (`fused_flow`). Both see such objects. A video ingest's splits read "dis_full"
(`fit_to_scene`); the flow term and spawning keep DIS (docs/real-footage.md, "A flow that sees
small objects"). Where the flow from a frame to the
next and the flow back disagree (occlusions, the smeared edges of a moving object, untextured
walls) it is left out: a forward-backward check, as in Sundaram et al. 2010.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

FlowMethod = Literal["dis", "dis_full", "fused"]  # what each is: the module's docstring
FLOW_PRESET = "medium"  # DIS preset: ~11 ms per 278x157 pair on two cores
# Farneback: 4 pyramid levels at half size each, 5x5 windows (small, so that a small object is
# not averaged with its surroundings), 5 iterations, polynomials over 5 px (sigma 1.1).
FARNEBACK = dict(pyr_scale=0.5, levels=4, winsize=5, iterations=5, poly_n=5, poly_sigma=1.1, flags=0)
WARP_WINDOW = 5  # px: the two flows' warping errors are compared as means over this window
DEPTH_SLACK = 1.05  # a Gaussian counts as visible when no deeper than this x the rendered depth
# Forward-backward check: a pixel's flow is kept where |F(p) + B(p + F(p))|^2 is at most
# FB_RELATIVE (|F|^2 + |B|^2) + FB_ABSOLUTE px^2 (Sundaram et al.'s 0.01 and 0.5).
FB_RELATIVE, FB_ABSOLUTE = 0.01, 0.5


def consistent(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """Where (H, W) the forward flow (H, W, 2) is confirmed by the backward flow sampled at the
    pixel it points to (bilinear; pixels pointing outside the image are not confirmed)."""
    import cv2

    H, W = forward.shape[:2]
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    tx, ty = gx + forward[..., 0], gy + forward[..., 1]
    back = cv2.remap(backward, tx, ty, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    err = ((forward + back) ** 2).sum(-1)
    bound = FB_RELATIVE * ((forward**2).sum(-1) + (back**2).sum(-1)) + FB_ABSOLUTE
    return (err <= bound) & (tx >= 0) & (tx <= W - 1) & (ty >= 0) & (ty <= H - 1)


def fused_flow(a: np.ndarray, b: np.ndarray, dis) -> np.ndarray:
    """Flow (H, W, 2) in pixels from grey frame `a` to `b` ((H, W) uint8): per pixel, DIS's
    (`dis`, an OpenCV DISOpticalFlow) or Farneback's (`FARNEBACK`), whichever warps `b` closer to
    `a` over a WARP_WINDOW square (ties: DIS)."""
    import cv2

    flows = (dis.calc(a, b, None), cv2.calcOpticalFlowFarneback(a, b, None, **FARNEBACK))
    H, W = a.shape
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    a32, b32 = a.astype(np.float32), b.astype(np.float32)
    errors = [
        cv2.boxFilter(
            np.abs(cv2.remap(b32, gx + f[..., 0], gy + f[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE) - a32),
            -1,
            (WARP_WINDOW,) * 2,
        )
        for f in flows
    ]
    return np.where((errors[1] < errors[0])[..., None], flows[1], flows[0])


def frame_flows(frames: list, only: set[str] | None = None, method: FlowMethod = "dis") -> dict[str, tuple[int, Tensor]]:
    """`{frame id: (index of the next frame of the same camera in time, flow (H, W, 2) in pixels)}`
    for every frame but each camera's last (or for those of ids in `only`), from grayscale
    frames (`method`: "dis", "dis_full" or "fused", above); NaN where the forward-backward check
    fails."""
    try:
        import cv2
    except ImportError as exc:  # a dependency of the package; a hand-made environment may lack it
        raise RuntimeError(
            "the optical flow (the flow term, spawning and the decompositions' reading) needs OpenCV: "
            "pip install opencv-python-headless (or train with --set lambda_flow=0 "
            "--set spawn_frames=0 --set flow_vote_share=0)"
        ) from exc
    dis = cv2.DISOpticalFlow_create(
        {
            "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
            "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
            "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
        }[FLOW_PRESET]
    )
    if method not in get_args(FlowMethod):
        raise ValueError(f"flow method must be one of {', '.join(get_args(FlowMethod))}, got {method!r}")
    if method == "dis_full":
        dis.setFinestScale(0)  # the preset stops at half resolution

    def flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return fused_flow(a, b, dis) if method == "fused" else dis.calc(a, b, None)

    by_camera: dict[int, list[int]] = {}
    for i, f in enumerate(frames):
        by_camera.setdefault(f.camera_id, []).append(i)
    out = {}
    for order in by_camera.values():
        order.sort(key=lambda i: frames[i].time)
        gray = {}

        def grey(i):
            if i not in gray:
                gray[i] = cv2.cvtColor((np.clip(frames[i].image(), 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
            return gray[i]

        for a, b in zip(order[:-1], order[1:]):
            if only is not None and frames[a].id not in only:
                continue
            if grey(a).shape != grey(b).shape:
                continue
            forward = flow(grey(a), grey(b))
            forward[~consistent(forward, flow(grey(b), grey(a)))] = np.nan
            out[frames[a].id] = (b, torch.from_numpy(forward))
            gray.pop(a)
    return out


def project(x: Tensor, viewmat: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel coordinates (N, 2) and camera depth (N,) of world points `x` (N, 3)."""
    cam = x @ viewmat[:3, :3].T + viewmat[:3, 3]
    z = cam[:, 2]
    uv = cam @ K.T
    return uv[:, :2] / z.clamp_min(1e-6)[:, None], z


def unproject(uv: Tensor, z: Tensor, viewmat: Tensor, K: Tensor) -> Tensor:
    """World points (N, 3) at pixel coordinates `uv` (N, 2) and camera depths `z` (N,): the
    inverse of `project`."""
    cam = torch.stack([(uv[:, 0] - K[0, 2]) / K[0, 0] * z, (uv[:, 1] - K[1, 2]) / K[1, 1] * z, z], -1)
    return (cam - viewmat[:3, 3]) @ viewmat[:3, :3]  # R^T (p - t), row-wise


def sample(image: Tensor, uv: Tensor) -> Tensor:
    """Bilinear samples (N, C) of `image` (H, W, C) at pixel coordinates `uv` (N, 2), pixel
    centres at integer coordinates (the rasteriser's convention)."""
    H, W = image.shape[:2]
    grid = torch.stack([(uv[:, 0] + 0.5) / W * 2 - 1, (uv[:, 1] + 0.5) / H * 2 - 1], -1)
    s = F.grid_sample(image.permute(2, 0, 1)[None].float(), grid[None, None], mode="bilinear", padding_mode="border", align_corners=False)
    return s[0, :, 0].T


def flow_residual(
    x_t: Tensor, x_next: Tensor, cam_t: tuple[Tensor, Tensor], cam_next: tuple[Tensor, Tensor], flow: Tensor, depth: Tensor
) -> Tensor:
    """Per visible Gaussian, the image motion it makes from this frame to the next (`x_t`,
    `x_next` (N, 3) world positions; `cam_*` = (viewmat, K)) minus the flow at its pixel (M, 2);
    `depth` (H, W, 1) is this frame's rendered depth (0 where nothing was drawn). Gaussians whose
    pixel touches a NaN flow (failed the forward-backward check) are left out."""
    uv_t, z_t = project(x_t, *cam_t)
    uv_n, _ = project(x_next, *cam_next)
    H, W = flow.shape[:2]
    inside = (z_t > 1e-4) & (uv_t[:, 0] >= 0) & (uv_t[:, 0] <= W - 1) & (uv_t[:, 1] >= 0) & (uv_t[:, 1] <= H - 1)
    # The rows kept are narrowed on detached values and gathered once, with index_select: the
    # backward of chained boolean indexing is one serial accumulating index_put per link.
    rows = torch.nonzero(inside).squeeze(1)
    uv, z = uv_t.detach()[rows], z_t.detach()[rows]
    d = sample(depth.detach(), uv)[:, 0]
    front = (d > 0) & (z <= DEPTH_SLACK * d)
    rows, uv = rows[front], uv[front]
    f = sample(flow, uv)
    ok = torch.isfinite(f).all(-1)
    rows = rows[ok]
    return (uv_n.index_select(0, rows) - uv_t.index_select(0, rows)) - f[ok]


def charbonnier(r: Tensor) -> Tensor:
    """Mean robust length of residuals `r` (N, 2) in pixels: ~|r| for large ones, so that flow
    errors at occlusions and on blur do not dominate."""
    if len(r) == 0:
        return r.sum() * 0
    return (torch.sqrt((r * r).sum(-1) + 1.0) - 1.0).mean()
