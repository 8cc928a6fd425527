"""Shared constants and containers of the rasteriser backends (mirrors csrc/kernels.h)."""

from __future__ import annotations

from dataclasses import dataclass, field

from torch import Tensor

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
EPS2D = 0.3  # default screen-space low-pass added to each 2D covariance's diagonal (pixels^2)


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities for one camera. Invisible Gaussians have
    `radii == 0` and zeros elsewhere."""

    means2d: Tensor  # (N, 2) pixel coordinates
    conics: Tensor  # (N, 3) inverse 2D covariance (a, b, c)
    depths: Tensor  # (N,) camera-space z
    opacities: Tensor  # (N,) opacity after anti-aliasing compensation
    radii: Tensor  # (N,) int32, pixels; 0 = culled
    bbox: Tensor  # (N, 4) int32 pixel box x0, y0, x1, y1 (exclusive end)


@dataclass
class Rendered:
    """What `rasterize` returns. Shapes for N Gaussians, C colour channels, an H x W image."""

    image: Tensor  # (H, W, C)
    alpha: Tensor  # (H, W, 1) accumulated opacity
    depth: Tensor  # (H, W, 1) expected depth (alpha-normalised; 0 where alpha ~ 0)
    radii: Tensor  # (N,) int32 screen-space radius in pixels, 0 if not drawn
    means2d: Tensor  # (N, 2) screen-space means; its .grad after backward feeds densification
    depths: Tensor  # (N,) camera-space depth of each mean
    conics: Tensor  # (N, 3)
    info: dict = field(default_factory=dict)  # backend extras, e.g. "means2d_absgrad" after backward

    def screen_grad(self, absgrad: bool = False) -> Tensor | None:
        """`(N, 2)` after backward: the loss's gradient at the screen-space means that
        densification reads (with `absgrad`, the sum of its per-pixel parts' absolute values);
        None before. gsplat's lives on its own `(1, N, 2)` tensor (`gsplat_backend`)."""
        source = self.info.get("gsplat_means2d")
        if source is not None:
            g = getattr(source, "absgrad", None) if absgrad else source.grad
            return None if g is None else g.reshape(-1, 2)
        return self.info.get("means2d_absgrad") if absgrad else self.means2d.grad

    @property
    def visible(self) -> Tensor:
        """(N,) bool: the Gaussian touched at least one tile of the image."""
        return self.radii > 0
