"""Pure-PyTorch rasteriser: the readable reference and the test oracle of the C++ backend.

It implements exactly the rules of `csrc/kernels.h` with autograd doing the backward. It is
slow and memory hungry (it evaluates every Gaussian of a tile row against every pixel of
it), so keep it to small scenes.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .covariance import covariance_from_quat_scale, pack_covariance
from .types import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE, Projection

_TRIU = ((0, 1, 2), (1, 3, 4), (2, 4, 5))


def unpack_covariance(cov6: Tensor) -> Tensor:
    """`(N, 6)` upper triangle -> `(N, 3, 3)` symmetric."""
    idx = torch.tensor(_TRIU, device=cov6.device).reshape(-1)
    return cov6[:, idx].reshape(-1, 3, 3)


def packed_covariance(quats: Tensor, scales: Tensor) -> Tensor:
    """`(N, 6)` packed `R S S^T R^T` from `(N, 4)` quaternions and `(N, 3)` scales."""
    return pack_covariance(covariance_from_quat_scale(quats, scales))


def camera_jacobian(
    means: Tensor, viewmat: Tensor, K: Tensor, width: int, height: int, near: float, far: float
) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-space positions `(N, 3)`, the in-depth-range mask `(N,)` and the perspective
    projection's Jacobian `(N, 2, 3)` with respect to camera-space position (3DGS's EWA rule,
    the ray direction clamped to 1.3x the field of view)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    in_depth = (z >= near) & (z <= far)
    # Invalid entries get harmless stand-ins so that masked-out values never produce NaN
    # gradients through torch.where.
    z = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    txz = torch.minimum(torch.maximum(x / z, -(cx / fx + 0.3 * tan_fovx)), (width - cx) / fx + 0.3 * tan_fovx)
    tyz = torch.minimum(torch.maximum(y / z, -(cy / fy + 0.3 * tan_fovy)), (height - cy) / fy + 0.3 * tan_fovy)
    zeros = torch.zeros_like(z)
    J = torch.stack([fx / z, zeros, -fx * txz / z, zeros, fy / z, -fy * tyz / z], dim=-1).reshape(-1, 2, 3)
    return p, in_depth, J


def project(
    means: Tensor,
    covars6: Tensor,
    opacities: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    near: float,
    far: float,
    eps2d: float,
    antialiased: bool,
) -> Projection:
    dtype = means.dtype
    viewmat = viewmat.to(means)
    K = K.to(means)
    R = viewmat[:3, :3]
    p, in_depth, J = camera_jacobian(means, viewmat, K, width, height, near, far)
    x, y, z = p.unbind(-1)
    z = torch.where(in_depth, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    cov_cam = R @ unpack_covariance(covars6) @ R.T
    cov2d = J @ cov_cam @ J.transpose(-1, -2)
    a0, q, c0 = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    pd, rd = a0 + eps2d, c0 + eps2d
    det0 = a0 * c0 - q * q
    det1 = pd * rd - q * q
    ok_det = torch.isfinite(det1) & (det1 > 0)
    det1 = torch.where(ok_det, det1, torch.ones_like(det1))
    if antialiased:
        pos = det0 > 0
        comp = torch.sqrt(torch.where(pos, det0, torch.ones_like(det0)) / det1)
        comp = torch.where(pos, comp, torch.zeros_like(comp))
    else:
        comp = torch.ones_like(det1)
    opac_eff = opacities * comp
    conics = torch.stack([rd / det1, -q / det1, pd / det1], dim=-1)
    u = fx * (x / z) + cx
    v = fy * (y / z) + cy
    means2d = torch.stack([u, v], dim=-1)

    with torch.no_grad():
        o64 = opac_eff.double()
        level = 2.0 * torch.log(o64.clamp_min(1e-300) / ALPHA_MIN)
        rx = torch.sqrt((level * pd.double()).clamp_min(0)).clamp_max(1e7)
        ry = torch.sqrt((level * rd.double()).clamp_min(0)).clamp_max(1e7)
        uu, vv = u.double().clamp(-1e9, 1e9), v.double().clamp(-1e9, 1e9)
        x0 = torch.floor(uu - rx).clamp_min(0)
        x1 = torch.ceil(uu + rx).clamp_max(width)
        y0 = torch.floor(vv - ry).clamp_min(0)
        y1 = torch.ceil(vv + ry).clamp_max(height)
        visible = in_depth & ok_det & torch.isfinite(u) & torch.isfinite(v) & (opac_eff >= ALPHA_MIN) & (x0 < x1) & (y0 < y1)
        radii = torch.where(visible, torch.ceil(torch.maximum(rx, ry)).clamp_min(1), 0).to(torch.int32)
        bbox = torch.stack([x0, y0, x1, y1], dim=-1).to(torch.int32) * visible[:, None]

    vis = visible.to(dtype)[:, None]
    return Projection(
        means2d=means2d * vis, conics=conics * vis, depths=p[:, 2] * vis[:, 0], opacities=opac_eff * vis[:, 0], radii=radii, bbox=bbox
    )


def blur_opacity_scale(means, covars6, sweep, viewmat, K, width, height, eps2d, near, far) -> Tensor:
    """Motion-blur footprint factor (arguments as `render/blur.py`'s), as a plain autograd expression."""
    with torch.no_grad():
        viewmat, K = viewmat.to(means), K.to(means)
        _, _, J = camera_jacobian(means, viewmat, K, width, height, near, far)
        M = J @ viewmat[:3, :3]  # world -> screen, (B, 2, 3), held constant
    cov2d = M @ unpack_covariance(covars6) @ M.transpose(1, 2)
    a, b, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d
    u, v = (M @ sweep[:, :, None]).squeeze(-1).unbind(-1)
    det = (a * c - b * b).clamp_min(1e-20)
    q = (c * u * u - 2 * b * u * v + a * v * v) / det  # s2ᵀ Σ2_blur⁻¹ s2
    # q / 12 < 1 exactly (Σ2_blur - s2 s2ᵀ/12 is positive definite); the clamp absorbs rounding.
    return (1 - q / 12).clamp_min(1e-6).sqrt()


def rasterize_to_pixels(
    proj: Projection, colors: Tensor, background: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor, Tensor, dict]:
    """Composites front to back. Returns image `(H, W, C)`, alpha `(H, W)`, the expected
    depth `(H, W)` (alpha-weighted depth sum over alpha; 0 where alpha <= 1e-6) and an
    (empty) info dict."""
    dtype = colors.dtype
    C = colors.shape[1]
    visible = proj.radii > 0
    order = torch.argsort(proj.depths.detach().masked_fill(~visible, math.inf), stable=True)
    order = order[: int(visible.sum())]
    m2d, con, opa = proj.means2d[order], proj.conics[order], proj.opacities[order]
    col, dep, box = colors[order], proj.depths[order], proj.bbox[order]

    rows = []
    for y0 in range(0, height, TILE):
        y1 = min(y0 + TILE, height)
        sel = (box[:, 1] < y1) & (box[:, 3] > y0)  # bounding box touches this band
        rows_at = torch.arange(y0, y1, dtype=dtype, device=m2d.device) + 0.5
        ys, xs = torch.meshgrid(rows_at, torch.arange(width, dtype=dtype, device=m2d.device) + 0.5, indexing="ij")
        pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1)  # (P, 2)
        d = pix[:, None, :] - m2d[sel][None]  # (P, G, 2)
        a, b, c = con[sel].unbind(-1)
        power = -0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) - b * d[..., 0] * d[..., 1]
        alpha = torch.clamp(opa[sel] * torch.exp(power), max=ALPHA_MAX)
        valid = (power <= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(valid, alpha, torch.zeros_like(alpha))
        one_minus = 1.0 - alpha
        t_incl = torch.cumprod(one_minus, dim=1)
        t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
        # A pixel stops at the first Gaussian that would take T below T_MIN, excluding it.
        included = valid & (t_incl >= T_MIN)
        w = torch.where(included, alpha * t_excl, torch.zeros_like(alpha))
        T_final = torch.where(included, one_minus, torch.ones_like(one_minus)).prod(dim=1)
        rows.append((w @ col[sel], T_final, w @ dep[sel]))
    acc = torch.cat([r[0] for r in rows]).reshape(height, width, C)
    T_final = torch.cat([r[1] for r in rows]).reshape(height, width)
    depth_acc = torch.cat([r[2] for r in rows]).reshape(height, width)
    image = acc + T_final[..., None] * background
    alpha = 1.0 - T_final
    depth = torch.where(alpha > 1e-6, depth_acc / alpha.clamp_min(1e-6), torch.zeros_like(depth_acc))
    return image, alpha, depth, {}
