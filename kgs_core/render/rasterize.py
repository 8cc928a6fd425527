"""`rasterize`: the one entry point of the Gaussian renderer."""

from __future__ import annotations

import warnings
from typing import Literal

import torch
from torch import Tensor

from . import _ext, cpu_backend, gsplat_backend, torch_backend
from .covariance import pack_covariance
from .sh import eval_sh
from .types import EPS2D, Rendered

Backend = Literal["auto", "cpu", "torch", "gsplat"]
_warned_fallback = False


def resolve_backend(backend: str, like: Tensor | None = None) -> str:
    """`auto` -> `cpu` when the C++ extension builds, else `torch` with a one-line warning.
    With `like` a tensor off the CPU (CUDA), the C++ kernels do not apply: `torch` (the
    rasteriser itself takes gsplat there, `rasterize`)."""
    global _warned_fallback
    if backend not in ("auto", "cpu", "torch", "gsplat"):
        raise ValueError(f"backend must be 'auto', 'cpu', 'torch' or 'gsplat', got {backend!r}")
    if like is not None and like.device.type != "cpu":
        if backend == "cpu":
            raise ValueError(f"backend 'cpu' (the C++ kernels) takes CPU tensors, got {like.device}")
        return "torch"
    if backend == "gsplat":
        raise ValueError("backend 'gsplat' (CUDA) takes CUDA tensors; these are on the CPU")
    if backend != "auto":
        return backend
    try:
        _ext.load()
        return "cpu"
    except _ext.ExtensionUnavailable as exc:
        if not _warned_fallback:
            warnings.warn(f"kgs: C++ rasteriser unavailable ({exc}); using the slow torch backend", stacklevel=3)
            _warned_fallback = True
        return "torch"


def packed_covariance(quats: Tensor, scales: Tensor, backend: Backend = "auto") -> Tensor:
    """`(N, 6)` packed `R S S^T R^T` (xx, xy, xz, yy, yz, zz) from `(N, 4)` wxyz quaternions
    (normalised here) and `(N, 3)` linear scales, differentiable; C++ on the `cpu` backend
    (~10x faster than the PyTorch expression on 15k Gaussians)."""
    impl = cpu_backend if resolve_backend(backend, quats) == "cpu" else torch_backend
    return impl.packed_covariance(quats, scales)


def rasterize(
    means: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    *,
    quats: Tensor | None = None,
    scales: Tensor | None = None,
    covars: Tensor | None = None,
    colors: Tensor | None = None,
    sh_coeffs: Tensor | None = None,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = EPS2D,
    antialiased: bool = False,
    absgrad: bool = False,
    backend: Backend = "auto",
) -> Rendered:
    """Renders N 3D Gaussians from one pinhole camera, differentiably.

    Args:
        means: `(N, 3)` world-space centres.
        opacities: `(N,)` or `(N, 1)` opacities in [0, 1] (already through the sigmoid).
        viewmat: `(4, 4)` world-to-camera `[R | t]`, OpenCV axes (x right, y down, z forward).
        K: `(3, 3)` intrinsics. Pixel (row i, col j) has its centre at `(j + 0.5, i + 0.5)`.
        width, height: image size in pixels.
        quats, scales: `(N, 4)` wxyz quaternions (normalised here) and `(N, 3)` linear scales;
            or
        covars: `(N, 3, 3)` world-space covariances (e.g. the kinematic refinement's output),
            or the same packed as `(N, 6)` upper triangles xx, xy, xz, yy, yz, zz
            (`packed_covariance`; what the model hands over, saving a pack per render).
        colors: `(N, C)` per-Gaussian colours (any C >= 1); or
        sh_coeffs: `(N, K, 3)` SH coefficients with `sh_degree` in 0..3 (`K >= (deg+1)^2`),
            evaluated toward the camera centre with the 3DGS `+0.5, clamp >= 0` convention.
        background: `(C,)` colour behind everything; zeros when omitted.
        near, far: depth range in camera z; Gaussians whose centre lies outside are culled.
        eps2d: screen-space low-pass added to the 2D covariance diagonal (pixels^2).
        antialiased: scale opacity by `sqrt(det(cov2d) / det(cov2d + eps2d I))` (Mip-Splatting)
            so that the dilation does not brighten small Gaussians.
        absgrad: after backward, also leave `info["means2d_absgrad"]` `(N, 2)`: per Gaussian
            the sum over pixels of |dL/dmean2d| (AbsGS densification). `cpu` backend only;
            it costs the backward about a fifth more, so it is off unless asked for.
        backend: `"cpu"` (C++), `"torch"` (reference), `"gsplat"` (CUDA, `gsplat_backend`)
            or `"auto"`: gsplat for CUDA tensors, else the C++ rasteriser when it builds.

    Returns:
        `Rendered` with `image (H, W, C)`, `alpha (H, W, 1)`, `depth (H, W, 1)`,
        `radii (N,)`, `means2d (N, 2)` (gradient retained for densification when the inputs
        require grad), `depths (N,)`, `conics (N, 3)` and backend `info`.

    Every input that is a floating tensor is differentiable, except the camera.
    """
    n = means.shape[0]
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be (N, 3), got {tuple(means.shape)}")
    if (covars is None) == (quats is None or scales is None):
        raise ValueError("give either covars, or both quats and scales")
    if (colors is None) == (sh_coeffs is None):
        raise ValueError("give exactly one of colors or sh_coeffs")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    opacities = opacities.reshape(n)
    on_gpu = means.device.type == "cuda"
    if on_gpu and backend in ("auto", "gsplat"):
        impl = gsplat_backend
    else:
        impl = cpu_backend if resolve_backend(backend, means) == "cpu" else torch_backend
    if absgrad and impl is torch_backend:
        raise ValueError("absgrad needs the cpu or gsplat backend")
    if covars is None:
        if quats.shape != (n, 4) or scales.shape != (n, 3):
            raise ValueError(f"quats must be (N, 4) and scales (N, 3), got {tuple(quats.shape)}, {tuple(scales.shape)}")
        cov6 = impl.packed_covariance(quats, scales)
    elif covars.shape == (n, 6):
        cov6 = covars
    elif covars.shape != (n, 3, 3):
        raise ValueError(f"covars must be (N, 3, 3) or packed (N, 6), got {tuple(covars.shape)}")
    else:
        cov6 = pack_covariance(covars)
    if colors is None:
        if sh_degree is None:
            raise ValueError("sh_coeffs needs sh_degree")
        cam_center = -viewmat[:3, :3].T @ viewmat[:3, 3]
        colors = eval_sh(sh_coeffs, means, cam_center.to(means), sh_degree)
    elif colors.ndim != 2 or colors.shape[0] != n:
        raise ValueError(f"colors must be (N, C), got {tuple(colors.shape)}")
    C = colors.shape[1]
    if background is None:
        background = torch.zeros(C, dtype=means.dtype, device=means.device)
    elif background.shape != (C,):
        raise ValueError(f"background must be ({C},), got {tuple(background.shape)}")

    if impl is gsplat_backend:
        return gsplat_backend.rasterize(
            means, cov6, opacities, colors, background, viewmat, K, width, height, near, far, eps2d, antialiased, absgrad
        )
    proj = impl.project(means, cov6, opacities, viewmat, K, width, height, near, far, eps2d, antialiased)
    if proj.means2d.requires_grad:
        proj.means2d.retain_grad()
    extra = {"absgrad": True} if absgrad else {}
    image, alpha, depth, info = impl.rasterize_to_pixels(proj, colors.to(means.dtype), background.to(means.dtype), width, height, **extra)
    return Rendered(
        image=image,
        alpha=alpha.unsqueeze(-1),
        depth=depth.unsqueeze(-1),
        radii=proj.radii,
        means2d=proj.means2d,
        depths=proj.depths,
        conics=proj.conics,
        info=info,
    )
