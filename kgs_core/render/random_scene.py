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
    """N Gaussians in a unit cube 3 units in front of a 60-degree camera, sized so that on
    average about `overlap` Gaussians cover each pixel (counting their 3-sigma footprints)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1
    means[:, 2] *= 0.5
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    K = intrinsics(width, height, 60.0, dtype=torch.float64)
    fx = float(K[0, 0])
    # The cube spans about 2 units at depth 3: fx * 2/3 pixels across. Pick the pixel radius r
    # with n * pi r^2 = overlap * width * height, then the world sigma r / (3 fx / depth).
    r_pix = math.sqrt(overlap * width * height / (n * math.pi))
    sigma = r_pix * 3.0 / (3.0 * fx)
    aniso = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64) * math.log(anisotropy))
    scales = sigma * aniso / aniso.prod(-1, keepdim=True) ** (1 / 3)
    opacities = 0.3 + 0.7 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    viewmat = look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0))
    return RandomScene(
        means.to(dtype), quats.to(dtype), scales.to(dtype), opacities.to(dtype), colors.to(dtype),
        viewmat.to(dtype), K.to(dtype), width, height,
    )
