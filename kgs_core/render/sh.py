"""Real spherical harmonics up to degree 3, evaluated per Gaussian for one camera."""

from __future__ import annotations

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(dirs: Tensor, degree: int) -> Tensor:
    """Basis values `(N, (degree+1)^2)` for unit directions `(N, 3)`."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [C2[0] * xy, C2[1] * yz, C2[2] * (2 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


class _ShColors(torch.autograd.Function):
    """`eval_sh` through the C++ extension (csrc/sh.cpp); gradient to the coefficients only."""

    @staticmethod
    def forward(ctx, sh_coeffs, means, center, degree):
        from . import _ext

        ctx.save_for_backward(sh_coeffs, means, center)
        ctx.degree = degree
        return _ext.load().sh_forward(sh_coeffs, means, center, degree)

    @staticmethod
    def backward(ctx, g_rgb):
        from . import _ext

        sh_coeffs, means, center = ctx.saved_tensors
        g = _ext.load().sh_backward(sh_coeffs, means, center, ctx.degree, g_rgb.contiguous())
        return g, None, None, None


def eval_sh(sh_coeffs: Tensor, means: Tensor, camera_center: Tensor, degree: int) -> Tensor:
    """Colours `(N, 3)` from SH coefficients `(N, K, 3)` seen from `camera_center` `(3,)`.

    Uses the first `(degree+1)^2` coefficients; adds 0.5 and clamps at 0 as 3DGS does, so a
    degree-0 coefficient `c` gives colour `C0 * c + 0.5`. The direction is not
    differentiated. Runs in C++ on CPU tensors when the extension is available, else
    `eval_sh_reference` (the same numbers: tested).
    """
    k = num_sh_bases(degree)
    if sh_coeffs.shape[1] < k:
        raise ValueError(f"sh_coeffs has {sh_coeffs.shape[1]} bases, degree {degree} needs {k}")
    from . import _ext

    if _ext.usable_for(sh_coeffs) and sh_coeffs.ndim == 3 and sh_coeffs.shape[2] == 3:
        dt = sh_coeffs.dtype
        return _ShColors.apply(
            sh_coeffs.contiguous(), means.detach().to(dt).contiguous(), camera_center.detach().to(dt).reshape(3).contiguous(), int(degree)
        )
    return eval_sh_reference(sh_coeffs, means, camera_center, degree)


def eval_sh_reference(sh_coeffs: Tensor, means: Tensor, camera_center: Tensor, degree: int) -> Tensor:
    """`eval_sh` in plain PyTorch (any device)."""
    k = num_sh_bases(degree)
    if sh_coeffs.shape[1] < k:
        raise ValueError(f"sh_coeffs has {sh_coeffs.shape[1]} bases, degree {degree} needs {k}")
    dirs = means.detach() - camera_center
    # A Gaussian at the camera centre has no direction; any unit vector gives finite colours.
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(dirs, degree)
    rgb = (basis.unsqueeze(-1) * sh_coeffs[:, :k]).sum(dim=1) + 0.5
    return rgb.clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient that reproduces `rgb` (inverse of `eval_sh` at degree 0)."""
    return (rgb - 0.5) / C0
