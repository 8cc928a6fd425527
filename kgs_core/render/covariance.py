"""Rotations and covariances of Gaussians."""

from __future__ import annotations

import torch
from torch import Tensor

# Indices of the upper triangle (xx, xy, xz, yy, yz, zz) of a 3x3 matrix.
TRIU_ROWS = (0, 0, 0, 1, 1, 2)
TRIU_COLS = (0, 1, 2, 1, 2, 2)


def normalize_quats(quats: Tensor, eps: float = 1e-12) -> Tensor:
    """Unit quaternions `(N, 4)` wxyz; a zero quaternion becomes the identity rotation."""
    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    small = norm < eps
    return torch.where(small, identity, quats / torch.where(small, torch.ones_like(norm), norm))


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices `(N, 3, 3)` from quaternions `(N, 4)` wxyz (normalised here)."""
    w, x, y, z = normalize_quats(quats).unbind(-1)
    # fmt: off
    rows = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]
    # fmt: on
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_from_quat_scale(quats: Tensor, scales: Tensor) -> Tensor:
    """`Sigma = R S S^T R^T` `(N, 3, 3)` from quaternions `(N, 4)` and linear scales `(N, 3)`."""
    M = quat_to_rotmat(quats) * scales.unsqueeze(-2)
    return M @ M.transpose(-1, -2)


# Positions of the packed entries in a row-major 3x3 matrix (the inverse of the packing).
UNPACK_INDEX = (0, 1, 2, 1, 3, 4, 2, 4, 5)


def unpack_covariance(cov6: Tensor) -> Tensor:
    """`(N, 6)` packed upper triangle (xx, xy, xz, yy, yz, zz) -> `(N, 3, 3)` symmetric."""
    return cov6[:, UNPACK_INDEX].reshape(cov6.shape[0], 3, 3)


def pack_covariance(covars: Tensor) -> Tensor:
    """`(N, 3, 3)` -> `(N, 6)` upper triangle of the symmetrised matrix.

    Symmetrising first gives each off-diagonal input entry half the gradient of the packed
    value, the same as using the full matrix (so both backends agree on input gradients).
    """
    sym = 0.5 * (covars + covars.transpose(-1, -2))
    return sym[:, TRIU_ROWS, TRIU_COLS]
