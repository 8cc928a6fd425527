"""The rasteriser on CUDA: gsplat's `rasterization()` (Apache-2.0), behind `rasterize()`'s
signature, returning the same `Rendered` (image, alpha, expected depth, radii, screen-space
means whose gradient densification reads, depths, conics).

gsplat is the optional extra `kinematics-gs[cuda]`; it is imported on first use, so the CPU
product never needs it. Conventions that match ours: OpenCV camera axes, pixel centres at +0.5,
the same packed upper-triangle covariances inside (it takes (N, 3, 3)), the 0.3 px² low-pass,
`antialiased` as Mip-Splatting's opacity compensation, expected depth normalised by alpha.
"""

from __future__ import annotations

from torch import Tensor

from ..device import CUDA_EXTRA
from .covariance import unpack_covariance
from .types import Rendered


class GsplatUnavailable(RuntimeError):
    """gsplat is not installed (or does not import): the message names the extra."""


def load_gsplat():
    """The `gsplat` module, or GsplatUnavailable naming the extra to install."""
    try:
        import gsplat
    except ImportError as exc:
        raise GsplatUnavailable(f"the CUDA rasteriser needs gsplat ({exc}): {CUDA_EXTRA}") from None
    return gsplat


def rasterize(
    means: Tensor,
    covars6: Tensor,
    opacities: Tensor,
    colors: Tensor,
    background: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float,
    antialiased: bool,
    absgrad: bool,
) -> Rendered:
    """One camera's image of N Gaussians through `gsplat.rasterization` (shapes as in
    `rasterize`; `colors (N, C)` already evaluated, `covars6 (N, 6)` packed). After backward,
    `Rendered.screen_grad()` is the screen-space gradient (with `absgrad`, gsplat's sum of its
    absolute per-pixel parts)."""
    gsplat = load_gsplat()
    dev, dtype = means.device, means.dtype
    render, alpha, meta = gsplat.rasterization(
        means=means,
        quats=None,
        scales=None,
        covars=unpack_covariance(covars6),  # gsplat takes (N, 3, 3) and packs them itself
        opacities=opacities,
        colors=colors,
        viewmats=viewmat.to(dev, dtype)[None],
        Ks=K.to(dev, dtype)[None],
        width=width,
        height=height,
        near_plane=near,
        far_plane=far,
        eps2d=eps2d,
        packed=False,
        backgrounds=None,
        render_mode="RGB+ED",
        absgrad=absgrad,
        rasterize_mode="antialiased" if antialiased else "classic",
    )
    image, depth, alpha = render[0, ..., :-1], render[0, ..., -1:], alpha[0]
    # The background goes under what was drawn (ours, like gsplat's, composites C + (1 - A) bg);
    # the depth channel is not composited with it.
    image = image + (1.0 - alpha) * background.to(image)
    # The gradient reaches gsplat's own (1, N, 2) tensor, not a view of it: `Rendered.screen_grad`
    # reads it there.
    means2d = meta["means2d"]
    if means2d.requires_grad:
        means2d.retain_grad()
    radii = meta["radii"][0]
    if radii.dim() == 2:  # newer gsplat gives an (x, y) radius per Gaussian
        radii = radii.max(dim=-1).values
    return Rendered(
        image=image,
        alpha=alpha,
        depth=depth,
        radii=radii.int(),
        means2d=means2d.detach()[0],
        depths=meta["depths"][0],
        conics=meta["conics"][0],
        info={"gsplat_means2d": means2d},
    )
