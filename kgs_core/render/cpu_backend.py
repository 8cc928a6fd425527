"""C++ rasteriser wrapped in autograd Functions (kernels in csrc/, built by _ext)."""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from . import _ext
from .types import Projection


class _Covar(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales):
        ctx.save_for_backward(quats, scales)
        return _ext.load().covar_forward(quats, scales)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_cov6):
        quats, scales = ctx.saved_tensors
        return tuple(_ext.load().covar_backward(quats, scales, g_cov6.contiguous()))


def packed_covariance(quats: Tensor, scales: Tensor) -> Tensor:
    """`(N, 6)` packed `R S S^T R^T` from `(N, 4)` quaternions and `(N, 3)` scales."""
    return _Covar.apply(quats.contiguous(), scales.contiguous())


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, covars6, opacities, viewmat, K, width, height, near, far, eps2d, aa):
        ext = _ext.load()
        means2d, conics, depths, opac_eff, radii, bbox = ext.project_forward(
            means, covars6, opacities, viewmat, K, width, height, near, far, eps2d, aa
        )
        ctx.save_for_backward(means, covars6, opacities, viewmat, K, radii)
        ctx.args = (width, height, near, far, eps2d, aa)
        ctx.mark_non_differentiable(radii, bbox)
        return means2d, conics, depths, opac_eff, radii, bbox

    @staticmethod
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, g_opac, _g_radii, _g_bbox):
        means, covars6, opacities, viewmat, K, radii = ctx.saved_tensors
        g_means, g_cov, g_op = _ext.load().project_backward(
            means,
            covars6,
            opacities,
            viewmat,
            K,
            *ctx.args,
            radii,
            g_means2d.contiguous(),
            g_conics.contiguous(),
            g_depths.contiguous(),
            g_opac.contiguous(),
        )
        return g_means, g_cov, g_op, *([None] * 8)


class _BlurScale(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, covars6, sweep, viewmat, K, width, height, near, far, eps2d):
        ctx.save_for_backward(means, covars6, sweep, viewmat, K)
        ctx.args = (width, height, near, far, eps2d)
        return _ext.load().blur_scale_forward(means, covars6, sweep, viewmat, K, width, height, near, far, eps2d)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_scale):
        means, covars6, sweep, viewmat, K = ctx.saved_tensors
        g_cov, g_sweep = _ext.load().blur_scale_backward(means, covars6, sweep, viewmat, K, *ctx.args, g_scale.contiguous())
        return None, g_cov, g_sweep, *([None] * 7)


def blur_opacity_scale(means, covars6, sweep, viewmat, K, width, height, eps2d, near, far) -> Tensor:
    """Motion-blur footprint factor (arguments as `render/blur.py`'s), C++ forward and backward."""
    return _BlurScale.apply(
        means.detach().contiguous(),
        covars6.contiguous(),
        sweep.contiguous(),
        viewmat,
        K,
        int(width),
        int(height),
        float(near),
        float(far),
        float(eps2d),
    )


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, bbox, lists, width, height, info, absgrad):
        # depth: the expected depth (alpha-weighted depth sum / alpha, 0 where alpha <= 1e-6).
        image, alpha, depth, t_final, n_contrib, records = _ext.load().raster_forward(
            means2d, conics, opacities, colors, depths, bbox, background, *lists, width, height
        )
        # The backward reads the per-pair records (parameters + colour) instead of the inputs.
        ctx.save_for_backward(records, background, *lists, t_final, n_contrib, alpha, depth)
        ctx.size = (means2d.shape[0], width, height)
        ctx.info = info
        ctx.absgrad = absgrad
        # Outputs outside the loss (training uses only the image) get None, not zero images.
        ctx.set_materialize_grads(False)
        return image, alpha, depth

    @staticmethod
    @once_differentiable
    def backward(ctx, g_image, g_alpha, g_depth):
        records, background, *lists, t_final, n_contrib, alpha, depth = ctx.saved_tensors
        if g_image is None:
            g_image = torch.zeros(*t_final.shape, background.numel(), dtype=t_final.dtype)
        # Through depth = depth_sum / alpha to the kernels' two per-pixel outputs.
        g_depth_sum = torch.empty(0, dtype=t_final.dtype)
        if g_depth is not None:
            drawn = alpha > 1e-6
            inv = torch.where(drawn, 1.0 / alpha.clamp_min(1e-6), torch.zeros_like(alpha))
            g_depth_sum = g_depth * inv
            g_alpha = -g_depth_sum * depth if g_alpha is None else g_alpha - g_depth_sum * depth
        if g_alpha is None:
            g_alpha = torch.empty(0, dtype=t_final.dtype)
        g_m2d, g_con, g_op, g_col, g_dep, abs_g = _ext.load().raster_backward(
            records,
            background,
            *lists,
            t_final,
            n_contrib,
            g_image.contiguous(),
            g_alpha.contiguous(),
            g_depth_sum.contiguous(),
            *ctx.size,
            ctx.absgrad,
        )
        if ctx.absgrad:
            ctx.info["means2d_absgrad"] = abs_g
        g_bg = (g_image * t_final.unsqueeze(-1)).sum(dim=(0, 1)) if ctx.needs_input_grad[5] else None
        return g_m2d, g_con, g_op, g_col, g_dep, g_bg, *([None] * 6)


def project(means, covars6, opacities, viewmat, K, width, height, near, far, eps2d, antialiased) -> Projection:
    dt = means.dtype
    means2d, conics, depths, opac, radii, bbox = _Project.apply(
        means.contiguous(),
        covars6.contiguous(),
        opacities.contiguous(),
        viewmat.detach().to(torch.float64).contiguous(),
        K.detach().to(torch.float64).contiguous(),
        int(width),
        int(height),
        float(near),
        float(far),
        float(eps2d),
        bool(antialiased),
    )
    assert means2d.dtype == dt
    return Projection(means2d, conics, depths, opac, radii, bbox)


def rasterize_to_pixels(
    proj: Projection, colors: Tensor, background: Tensor, width: int, height: int, absgrad: bool = False
) -> tuple[Tensor, Tensor, Tensor, dict]:
    ext = _ext.load()
    lists = ext.bin_gaussians(proj.bbox, proj.radii, proj.depths.detach().contiguous(), width, height)
    info: dict = {"tile_offsets": lists[0], "tile_ranks": lists[1], "depth_order": lists[2]}
    image, alpha, depth = _Rasterize.apply(
        proj.means2d,
        proj.conics,
        proj.opacities,
        colors.contiguous(),
        proj.depths,
        background.contiguous(),
        proj.bbox,
        tuple(lists),
        int(width),
        int(height),
        info,
        bool(absgrad),
    )
    return image, alpha, depth, info


class _KPlanes(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, t, *grids):
        planes = [g[0] for g in grids]  # (1, F, H, W) parameters -> (F, H, W) views
        ctx.save_for_backward(x, t, *planes)
        return _ext.load().kplanes_forward(x, t, planes)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_out):
        x, t, *planes = ctx.saved_tensors
        g_x, *g_planes = _ext.load().kplanes_backward(x, t, planes, g_out.contiguous(), ctx.needs_input_grad[0])
        return (g_x if ctx.needs_input_grad[0] else None), None, *(g[None] for g in g_planes)


def kplanes_features(x: Tensor, t: Tensor, grids: list[Tensor]) -> Tensor:
    """K-Planes features `(M N, F R)` of the points `x (N, 3)` at the times `t (M N,)` (both
    normalised to [-1, 1], row `j` is point `j mod N`), from `R x 6` planes `(1, F, H, W)` in
    the order (xy, xz, xt, yz, yt, zt) per resolution; differentiable in `x` and the planes.
    `KPlanes.at_times` in kgs_core/model/deformation.py is the PyTorch reference."""
    return _KPlanes.apply(x.contiguous(), t.contiguous(), *grids)
