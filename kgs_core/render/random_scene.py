"""Random Gaussian scenes for tests, benchmarks and the smoke-test render."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .camera import intrinsics, look_at


@dataclass
class RandomScene:
    means: Tensor  # (N, 3)
    quats: Tensor  # (N, 4)
    scales: Tensor  # (N, 3)
    opacities: Tensor  # (N,)
    colors: Tensor  # (N, 3)
    viewmat: Tensor  # (4, 4)
    K: Tensor  # (3, 3)
    width: int
    height: int

    def tensors(self) -> list[Tensor]:
        return [self.means, self.quats, self.scales, self.opacities, self.colors]


def random_scene(
    n: int,
    width: int = 64,
    height: int = 64,
    overlap: float = 30.0,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    anisotropy: float = 3.0,
) -> RandomScene:
    """N Gaussians in a unit cube 3 units in front of a 60-degree camera, sized so that about
    `overlap` Gaussians reach alpha >= 1/255 at each pixel on average (the "Gaussians per
    pixel" of the rasteriser benchmark; it ignores early termination)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    means[:, 2] *= 0.5
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    K = intrinsics(width, height, 60.0, dtype=torch.float64)
    fx = float(K[0, 0])
    opacities = 0.3 + 0.7 * torch.rand(n, generator=g, dtype=torch.float64)
    # A Gaussian with pixel std s and opacity o covers pi * 2 ln(255 o) * (s^2 + 0.3) pixels
    # at alpha >= 1/255 (0.3: the rasteriser's low-pass dilation). Solve for s.
    mean_level = float((2 * torch.log(255 * opacities)).mean()) if n else 1.0
    s2 = overlap * width * height / (max(n, 1) * math.pi * mean_level) - 0.3
    # The cube's projection fills part of the frame and the perspective spreads sizes; the
    # 0.8 calibrates the average to `overlap` (checked by the benchmark's own measurement).
    sigma = math.sqrt(max(s2, 0.01) * 0.8) * 3.0 / fx
    aniso = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64) * math.log(anisotropy))
    scales = sigma * aniso / aniso.prod(-1, keepdim=True) ** (1 / 3)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    viewmat = look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    return RandomScene(
        means.to(dtype),
        quats.to(dtype),
        scales.to(dtype),
        opacities.to(dtype),
        colors.to(dtype),
        viewmat.to(dtype),
        K.to(dtype),
        width,
        height,
    )
