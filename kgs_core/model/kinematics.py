"""Kinematic basis and kinematics-guided covariance refinement (paper §4.3-4.4, appendix A.1).

Everything here is batched over Gaussians and differentiable with finite gradients at the
degenerate inputs (zero velocity, zero rotation vector): see tests/test_stability.py (the basis,
the refined covariance and its gradients at stiff and extreme inputs) and tests/test_model.py.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor

from ..render import packed_covariance
from ..render.covariance import normalize_quats

if TYPE_CHECKING:
    from .deformation import Offsets

Basis = Literal["paper", "duff", "principal"]

EPS = 1e-8  # normalisation guard of the in-plane axes
# Direction of motion: u_z = v / sqrt(|v|^2 + EPS_DIR^2) instead of the paper's v / (|v| + 1e-8).
# The paper's form is off unit length by eps/|v| (1 % at |v| = 1e-6); this one by
# EPS_DIR^2 / (2 |v|^2) (5e-7 at |v| = 1e-6), with the same finite gradient at v = 0
# (docs/stability.md).
EPS_DIR = 1e-9


def safe_norm(v: Tensor, eps: float = 1e-12) -> Tensor:
    """|v| along the last axis with a finite gradient at v = 0 (gradient 0 there)."""
    return torch.sqrt((v * v).sum(-1) + eps * eps)


def kinematic_basis(v: Tensor, basis: Basis = "paper", sigma: Tensor | None = None) -> Tensor:
    """`(N, 3, 3)` rotation `[u_x | u_y | u_z]` with `u_z` along the velocity `v (N, 3)`.

    * `paper`: reference `e_x`, switched to `e_y` when `|u_z . e_x| > 0.99` (appendix A.1).
      The switch makes the basis jump (a roll about `u_z`) across that threshold.
    * `duff`: the branch-free construction of Duff et al. (2017). No tangent frame on the
      sphere is continuous everywhere (hairy-ball theorem); this one jumps where `u_z` crosses
      the plane z = 0 instead of at the paper's 0.99 cap.
    For `v = 0` `u_z` is 0 and the basis degenerates; callers blend it away (see
    `refine_covariance`).
    """
    uz = v / safe_norm(v, EPS_DIR)[..., None]
    if basis in ("paper", "principal"):
        ex = torch.zeros_like(uz)
        ex[..., 0] = 1.0
        ey = torch.zeros_like(uz)
        ey[..., 1] = 1.0
        switch = (uz[..., 0].abs() > 0.99)[..., None]
        ref = torch.where(switch, ey, ex)
        ux = torch.linalg.cross(uz, ref)
        ux = ux / safe_norm(ux, EPS)[..., None]
        uy = torch.linalg.cross(uz, ux)
        if basis == "principal":
            if sigma is None:
                raise ValueError("basis 'principal' needs the covariance sigma")
            ux, uy = principal_roll(ux, uy, sigma)
    elif basis == "duff":
        n = uz / safe_norm(uz, EPS)[..., None]  # unit even where |v| ~ eps
        x, y, z = n.unbind(-1)
        sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
        a = -1.0 / (sign + z)
        b = x * y * a
        ux = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)
        uy = torch.stack([b, sign + y * y * a, -y], -1)
        scale = safe_norm(uz)[..., None]  # keeps the v = 0 degeneracy identical to `paper`
        ux, uy = ux * scale, uy * scale
    else:
        raise ValueError(f"basis must be 'paper', 'duff' or 'principal', got {basis!r}")
    return torch.stack([ux, uy, uz], dim=-1)


def principal_roll(ux: Tensor, uy: Tensor, sigma: Tensor, eps: float = 1e-30) -> tuple[Tensor, Tensor]:
    """Rotates `(ux, uy)` within their plane onto the principal axes of `sigma`'s projection
    `[[a, b], [b, c]]`: angle `0.5 atan2(2b, a - c)`. Where the projection is isotropic the
    angle is irrelevant (every roll gives the same refined covariance); the guard only keeps
    atan2's gradient finite there."""
    a = torch.einsum("ni,nij,nj->n", ux, sigma, ux)
    b = torch.einsum("ni,nij,nj->n", ux, sigma, uy)
    c = torch.einsum("ni,nij,nj->n", uy, sigma, uy)
    num, den = 2 * b, a - c
    iso = num.abs() + den.abs() <= eps
    theta = 0.5 * torch.atan2(torch.where(iso, torch.zeros_like(num), num), torch.where(iso, torch.ones_like(den), den))
    ct, st = torch.cos(theta)[..., None], torch.sin(theta)[..., None]
    return ct * ux + st * uy, ct * uy - st * ux


def rotvec_to_quat(w: Tensor) -> Tensor:
    """Unit quaternions `(N, 4)` wxyz of the rotation vectors `(N, 3)`: `R(q) = so3_exp(w)`."""
    theta = w.norm(dim=-1, keepdim=True)
    half = 0.5 * theta
    # sin(theta/2)/theta, with its series below 1e-4 rad
    k = torch.where(theta < 1e-4, 0.5 - theta * theta / 48, torch.sin(half) / theta.clamp_min(1e-12))
    return torch.cat([torch.cos(half), k * w], -1)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product `a b` of quaternions `(N, 4)` wxyz: `R(a b) = R(a) R(b)`."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def so3_exp(w: Tensor) -> Tensor:
    """Rotation matrices `(N, 3, 3)` from rotation vectors `(N, 3)` (Rodrigues), with Taylor
    series below 1e-3 rad so that values and gradients stay accurate near 0."""
    theta2 = (w * w).sum(-1)
    small = theta2 < 1e-6
    theta2_safe = torch.where(small, torch.ones_like(theta2), theta2)
    theta = torch.sqrt(theta2_safe)
    A = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(theta) / theta)
    B = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, (1 - torch.cos(theta)) / theta2_safe)
    zero = torch.zeros_like(w[..., 0])
    Kx = torch.stack([zero, -w[..., 2], w[..., 1], w[..., 2], zero, -w[..., 0], -w[..., 1], w[..., 0], zero], -1)
    Kx = Kx.reshape(w.shape[:-1] + (3, 3))
    eye = torch.eye(3, dtype=w.dtype).expand_as(Kx)
    return eye + A[..., None, None] * Kx + B[..., None, None] * (Kx @ Kx)


def refine_covariance(
    sigma: Tensor,
    v: Tensor,
    blur_len: Tensor,
    delta_s: Tensor,
    delta_r: Tensor,
    r_z: Tensor,
    kappa: Tensor,
    frame_len: Tensor,
    basis: Basis = "paper",
    lambda_s: float = 0.1,
    still_len: float = 1e-3,
) -> Tensor:
    """Kinematics-guided covariance `(N, 3, 3)`.

    Args:
        sigma: `(N, 3, 3)` covariance predicted for the Gaussian (SPD).
        v: `(N, 3)` velocity.
        blur_len: `(N,)` `|v| dt * exposure`, the path length during the exposure (0 = sharp).
        delta_s, delta_r: `(N, 3)` residual log-scale and rotation vector from the network.
        r_z: `(N, 3)` principal axis of the predicted rotation.
        kappa: scalar; `sigmoid(kappa)` is the lower bound of the alignment factor eta.
        frame_len: `(N,)` `|v| dt`, how far the Gaussian moves in one frame.
        still_len: below this per-frame motion the velocity direction is noise, so the result
            blends toward `sigma` with weight `frame_len^2 / (frame_len^2 + still_len^2)`; 0:
            no blend (the paper's).

    Steps (paper eqs. 9-14): `sigma_k^2 = u_k^T Sigma u_k`; `s' = (sigma_x, sigma_y, sigma_z +
    eta * blur_len)`; `eta = max(|r_z . u_z|, sigmoid(kappa))`; `log s = log s' + lambda_s *
    delta_s`; `R = R_kin exp(delta_r)`; `Sigma_kin = R S S^T R^T`.
    """
    Rk = kinematic_basis(v, basis, sigma)
    var = torch.einsum("nik,nij,njk->nk", Rk, sigma, Rk)  # u_k^T Sigma u_k per column k
    s_prime = torch.sqrt(var.clamp_min(0) + 1e-20)
    uz = Rk[..., 2]
    eta = torch.maximum((r_z * uz).sum(-1).abs(), torch.sigmoid(kappa).expand_as(blur_len))
    s_prime = torch.cat([s_prime[..., :2], (s_prime[..., 2] + eta * blur_len)[..., None]], -1)
    log_s = torch.log(s_prime.clamp_min(1e-10)) + lambda_s * delta_s
    R = Rk @ so3_exp(delta_r)
    M = R * torch.exp(log_s)[..., None, :]
    sigma_kin = M @ M.transpose(-1, -2)
    if still_len <= 0:
        return sigma_kin
    w = (frame_len * frame_len / (frame_len * frame_len + still_len * still_len))[..., None, None]
    return (1 - w) * sigma + w * sigma_kin


def motion_blur_covariance(cov6: Tensor, sweep: Tensor) -> Tensor:
    """Packed `(N, 6)` covariance of a Gaussian `cov6 (N, 6)` that moves by `sweep = v
    exposure_time (N, 3)` during the exposure, averaged over it: the Gaussian convolved with a
    uniform segment of length `L = |s|` along `s`, matched in its second moment:
    `Σ + (L² / 12) u uᵀ = Σ + s sᵀ / 12`.

    The `convolve` form of the kinematic refinement (docs/method.md): blur becomes elongation
    along the motion as in the paper, but without projecting `Σ` onto the kinematic frame
    (which drops its off-diagonal terms), so a sharp render (`sweep = 0`) is exactly `Σ` and the
    form needs no basis: it is smooth at `v = 0` and has no reference-axis switch. Packed,
    because every covariance the renderer takes is (unpacking the static Gaussians under camera
    blur, most of N, to `(N, 3, 3)` and back cost milliseconds a step)."""
    # Products of columns, not `sweep[:, rows] * sweep[:, cols]`: advanced indexing's backward is
    # an accumulating index_put, serial on CPU, and this runs on every Gaussian under camera blur.
    x, y, z = (sweep / 12.0**0.5).unbind(1)
    return cov6 + torch.stack([x * x, x * y, x * z, y * y, y * z, z * z], 1)


def velocity_from_offsets(offs: list, h: float, dt: float) -> Tensor:
    """The velocities K.R. builds on, from the field's `Offsets` at one or three times. One
    sample (`paper`): v = dx_t / dt, the offset from the canonical position over one frame.
    Three samples at t, t + h, t - h (`physical`): the
    central difference of the deformed position over the exposure (`h` at least half a frame,
    so that short exposures do not amplify noise); the canonical position cancels."""
    if len(offs) == 1:
        return offs[0].dx / dt
    return (offs[1].dx - offs[2].dx) / (2 * h)


def residual_covariance(quats: Tensor, scales: Tensor, off: "Offsets", lambda_s: float) -> Tensor:
    """D3DGS-style deformed covariance, packed `(N, 6)`: canonical rotation times `exp(dr)`,
    scales times `exp(lambda_s ds)`. The rotations compose as quaternions and the covariance is
    `packed_covariance`'s (C++ when built): `R(q) so3_exp(dr)` and `M Mᵀ` to float rounding,
    without batched 3x3 products, slow on a CPU (docs/results.md, "Training speed")."""
    rotation = quat_multiply(normalize_quats(quats), rotvec_to_quat(off.dr))
    return packed_covariance(rotation, scales * torch.exp(lambda_s * off.ds))
