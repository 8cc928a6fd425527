"""Deformation field `F_theta(x, t) -> (dx, dr, ds)`: K-Planes features and a small MLP
(4DGaussians' defaults: spatial 64^3 at multi-resolution (1, 2), temporal 25, width 64, one
hidden layer), plus the fine residual MLP `g_phi(f_i, gamma(t))` of the coarse-to-fine scheme
and the appendix's time-noise schedule."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..render import resolve_backend
from ..render.cpu_backend import kplanes_features


class KPlanes(nn.Module):
    """Six feature planes (xy, xz, yz, xt, yt, zt) per resolution; features are the product
    over planes, concatenated over resolutions."""

    def __init__(self, spatial: int = 64, temporal: int = 25, features: int = 32, multires=(1, 2), bound: float = 1.5):
        super().__init__()
        self.bound = bound
        self.pairs = list(itertools.combinations(range(4), 2))  # (0,1) (0,2) (0,3) (1,2) (1,3) (2,3)
        self.grids = nn.ParameterList()
        for m in multires:
            for a, b in self.pairs:
                ra = temporal if a == 3 else spatial * m
                rb = temporal if b == 3 else spatial * m
                if 3 in (a, b):
                    # Time planes start at 1: no temporal variation until the data asks for it.
                    init = torch.ones(1, features, rb, ra)
                else:
                    init = torch.empty(1, features, rb, ra).uniform_(0.1, 0.5)
                self.grids.append(nn.Parameter(init))
        self.n_res = len(multires)
        self.out_dim = features * len(multires)

    def forward(self, x: Tensor, t: Tensor) -> Tensor:
        """`x (N, 3)` world points (clamped to +-bound), `t (N,)` in [0, 1] -> `(N, out_dim)`."""
        return self.at_times(x, [t])

    def at_times(self, x: Tensor, times: list[Tensor], backend: str = "auto") -> Tensor:
        """The features of the points `x (N, 3)` at each of `times` (M tensors `(N,)`) ->
        `(M N, out_dim)`, time-major. `backend`: `cpu` is the fused C++ kernel
        (`kplanes_features`), `torch` the grid_sample expression below (its test oracle),
        `auto` the first when the extension builds."""
        n, m = len(x), len(times)
        xn = (x / self.bound).clamp(-1, 1)
        tn = (torch.cat(times) * 2 - 1).clamp(-1, 1)
        if n and x.dtype == torch.float32 and resolve_backend(backend, x) == "cpu":
            return kplanes_features(xn, tn, list(self.grids))
        # The three spatial planes do not depend on t: sampled once for all M times (the
        # physical velocity needs three times per step).
        coords = torch.cat([xn.repeat(m, 1), tn[:, None]], -1)  # (M N, 4)
        feats = []
        for r in range(self.n_res):
            space, time = None, None
            for k, (a, b) in enumerate(self.pairs):
                grid = self.grids[r * 6 + k]
                uv = (coords[:, [a, b]] if b == 3 else coords[:n, [a, b]]).reshape(1, -1, 1, 2)
                sample = F.grid_sample(grid, uv, mode="bilinear", padding_mode="border", align_corners=True)
                sample = sample.view(grid.shape[1], -1).t()
                if b == 3:
                    time = sample if time is None else time * sample
                else:
                    space = sample if space is None else space * sample
            feats.append(space.repeat(m, 1) * time)
        return torch.cat(feats, -1)

    def smoothness(self) -> Tensor:
        """Total variation of the planes (K-Planes' regulariser), small weight in training."""
        tv = 0.0
        for g in self.grids:
            tv = tv + (g[..., 1:, :] - g[..., :-1, :]).pow(2).mean() + (g[..., :, 1:] - g[..., :, :-1]).pow(2).mean()
        return tv


def _mlp(inp: int, width: int, out: int, depth: int = 1) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = inp
    for _ in range(depth):
        layers += [nn.Linear(d, width), nn.ReLU()]
        d = width
    last = nn.Linear(d, out)
    nn.init.zeros_(last.weight)  # start as the identity deformation
    nn.init.zeros_(last.bias)
    layers.append(last)
    return nn.Sequential(*layers)


@dataclass
class Offsets:
    dx: Tensor  # (N, 3)
    dr: Tensor  # (N, 3) rotation vector
    ds: Tensor  # (N, 3) log-scale residual

    def __add__(self, other: "Offsets") -> "Offsets":
        return Offsets(self.dx + other.dx, self.dr + other.dr, self.ds + other.ds)

    def index(self, idx) -> "Offsets":
        return Offsets(self.dx[idx], self.dr[idx], self.ds[idx])

    @staticmethod
    def zeros(n: int, dtype=torch.float32) -> "Offsets":
        z = torch.zeros(n, 3, dtype=dtype)
        return Offsets(z, z, z)

    def cat(self) -> Tensor:
        return torch.cat([self.dx, self.dr, self.ds], -1)

    @staticmethod
    def from_cat(x: Tensor) -> "Offsets":
        return Offsets(x[..., :3], x[..., 3:6], x[..., 6:9])


class DeformationField(nn.Module):
    def __init__(
        self,
        spatial: int = 64,
        temporal: int = 25,
        features: int = 32,
        multires=(1, 2),
        width: int = 64,
        depth: int = 1,
        bound: float = 1.5,
    ):
        super().__init__()
        self.planes = KPlanes(spatial, temporal, features, multires, bound)
        self.mlp = _mlp(self.planes.out_dim, width, 9, depth)

    def forward(self, x: Tensor, t: Tensor) -> Offsets:
        return Offsets.from_cat(self.mlp(self.planes(x, t)))

    def at_times(self, x: Tensor, times: list[Tensor]) -> list[Offsets]:
        """Offsets of `x (N, 3)` at each of `times` (M tensors `(N,)`): one batched evaluation."""
        out = self.mlp(self.planes.at_times(x, times))
        return [Offsets.from_cat(chunk) for chunk in out.split(len(x))]


def fourier_time(t: Tensor, n_freqs: int = 6) -> Tensor:
    """gamma(t): `(N, 1 + 2 n_freqs)` sinusoidal encoding."""
    freqs = (2.0 ** torch.arange(n_freqs, dtype=t.dtype)) * math.pi
    a = t[:, None] * freqs
    return torch.cat([t[:, None], torch.sin(a), torch.cos(a)], -1)


class FineResidual(nn.Module):
    """`g_phi(f_i, gamma(t))`: a shared MLP on a learnable per-Gaussian feature."""

    def __init__(self, feature_dim: int = 16, width: int = 64, n_freqs: int = 6):
        super().__init__()
        self.n_freqs = n_freqs
        self.mlp = _mlp(feature_dim + 1 + 2 * n_freqs, width, 9, depth=1)

    def forward(self, features: Tensor, t: Tensor) -> Offsets:
        return Offsets.from_cat(self.mlp(torch.cat([features, fourier_time(t, self.n_freqs)], -1)))


class TimeOpacity(nn.Module):
    """`o_phi(f_i, gamma(t))`: an offset (N,) to each dynamic Gaussian's opacity logit at time
    `t`, from the fine residual's per-Gaussian feature. Zero at the start (the last layer is
    zero-initialised): every Gaussian is as opaque at every time as the paper's, until the loss
    fades one where the field puts it wrong (a ghost of a head the field could not follow)."""

    def __init__(self, feature_dim: int = 16, width: int = 64, n_freqs: int = 6):
        super().__init__()
        self.n_freqs = n_freqs
        self.mlp = _mlp(feature_dim + 1 + 2 * n_freqs, width, 1, depth=1)

    def forward(self, features: Tensor, t: Tensor) -> Tensor:
        return self.mlp(torch.cat([features, fourier_time(t, self.n_freqs)], -1))[:, 0]


@dataclass
class TimeNoise:
    """Appendix B: sigma(k) = w(k) [sigma_init (1 - kappa) + sigma_final kappa], kappa = k / K_max,
    with a sine warm-up w(k) from w_delay to 1 over K_delay iterations. Units: normalised time."""

    sigma_init: float
    sigma_final: float
    k_max: int
    k_delay: int = 0
    w_delay: float = 0.1

    def sigma(self, k: int) -> float:
        kappa = min(max(k / max(self.k_max, 1), 0.0), 1.0)
        w = 1.0
        if k < self.k_delay:
            w = self.w_delay + (1 - self.w_delay) * math.sin(0.5 * math.pi * k / self.k_delay)
        return w * (self.sigma_init * (1 - kappa) + self.sigma_final * kappa)
