"""Small camera helpers (OpenCV convention: x right, y down, z forward)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def look_at(eye, target, up=(0.0, -1.0, 0.0), dtype=torch.float32) -> Tensor:
    """World-to-camera `(4, 4)` for a camera at `eye` looking at `target`; `up` is the world
    direction that appears up in the image (OpenCV's y axis points down, hence the default)."""
    eye, target, up = (torch.as_tensor(v, dtype=torch.float64) for v in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(-up, z)
    if x.norm() < 1e-9:  # looking along `up`: pick any perpendicular
        x = torch.linalg.cross(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), z)
        if x.norm() < 1e-9:
            x = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), z)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ eye
    return viewmat.to(dtype)


def intrinsics(width: int, height: int, fov_x_deg: float = 60.0, dtype=torch.float32) -> Tensor:
    """Pinhole `K (3, 3)` with square pixels and the principal point at the image centre."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    return torch.tensor([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]], dtype=dtype)
