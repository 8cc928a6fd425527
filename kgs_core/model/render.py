"""Rendering a model from a camera at a time: the one place that turns `KinematicsGS` into a
`rasterize` call (training, evaluation, the server and the exporters all use it)."""

from __future__ import annotations

import dataclasses

import torch

from ..data.scene import Camera
from ..render import rasterize
from ..render.blur import blurred_opacities
from ..render.covariance import pack_covariance, unpack_covariance
from ..render.types import Rendered
from .dynamic import KinematicsGS
from .gaussians import GaussiansAt


def camera_tensors(cam: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.tensor(cam.viewmat, dtype=torch.float32), torch.tensor(cam.K, dtype=torch.float32)


def render_model(
    model: KinematicsGS,
    cam: Camera,
    t: float,
    exposure: float = 0.0,
    dt: float = 1.0,
    background: torch.Tensor | None = None,
    colors: torch.Tensor | None = None,
    noise: float = 0.0,
    static: bool = False,
    camera_motion=None,
    velocity: bool = True,
    world_transform: tuple[torch.Tensor, torch.Tensor] | None = None,
    absgrad: bool = False,
) -> tuple[Rendered, GaussiansAt]:
    """Renders `model` at time `t` from `cam`. `exposure` 0 renders sharp; `colors (N, C)`
    replaces the SH colours (e.g. a dynamic-flag channel); `static` skips the deformation
    (the static 3DGS baseline); `camera_motion` blurs along the camera's own motion as well
    (`KinematicsGS.at`); Gaussians the convolve form blurs (`exposure` > 0) have their
    opacities scaled to keep each splat's 2D mass (`blurred_opacities`); `velocity=False` when
    the caller does not read `g.velocity` (lets a sharp render skip the physical velocity's
    extra field samples); `world_transform = (R, t)` moves every Gaussian rigidly before
    rasterising (a training camera's pose correction, `train/pose_refine.py`); `absgrad` asks
    the rasteriser for the per-pixel absolute screen gradients after backward (`rasterize`)."""
    g = model.at_static() if static else model.at(t, exposure=exposure, dt=dt, noise=noise, camera_motion=camera_motion, velocity=velocity)
    if world_transform is not None:
        g = transform_gaussians(g, *world_transform)
    viewmat, K = camera_tensors(cam)
    opacities = g.opacities
    if g.sweep is not None:  # blurred splats keep their 2D mass (render/blur.py)
        opacities = blurred_opacities(opacities, g.means, g.covars6, g.sweep, viewmat, K, cam.width, cam.height)
    if colors is not None:
        kw = dict(colors=colors)
    else:
        kw = dict(sh_coeffs=g.sh, sh_degree=model.config.sh_degree, background=background if background is not None else torch.zeros(3))
    out = rasterize(g.means, opacities, viewmat, K, cam.width, cam.height, covars=g.covars6, absgrad=absgrad, **kw)
    return out, g


def transform_gaussians(g: GaussiansAt, R: torch.Tensor, t: torch.Tensor) -> GaussiansAt:
    """`g` moved rigidly, `x -> R x + t`: means, covariances and blur sweeps."""
    sweep = None if g.sweep is None else (g.sweep[0], g.sweep[1] @ R.T)
    return dataclasses.replace(g, means=g.means @ R.T + t, covars6=pack_covariance(R @ unpack_covariance(g.covars6) @ R.T), sweep=sweep)
