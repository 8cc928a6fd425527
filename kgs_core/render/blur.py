"""Motion blur as a splat's elongation, made mass-preserving.

The convolve form of the kinematic refinement (`model/kinematics.py: motion_blur_covariance`,
on packed covariances) blurs a Gaussian that sweeps `s` during the exposure by adding the
sweep's second moment to its covariance, `Σ_blur = Σ + s sᵀ / 12`. On screen that widens the
splat but keeps its peak opacity, so its footprint (opacity times the 2D Gaussian's area) grows by
`sqrt(det Σ2_blur / det Σ2)`: a blurred splat would cover more than the Gaussian does over
the exposure. Physically the exposure averages the sharp splat along its path, which
conserves that footprint; `blur_opacity_scale` is the factor that restores it.
"""

from __future__ import annotations

from torch import Tensor

from . import cpu_backend, torch_backend
from .rasterize import Backend, resolve_backend
from .types import EPS2D


def blur_opacity_scale(
    means: Tensor,
    covars6: Tensor,
    sweep: Tensor,
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
    eps2d: float = EPS2D,
    near: float = 0.01,
    far: float = 1e10,
    backend: Backend = "auto",
) -> Tensor:
    """`(B,)` opacity factors for B blurred Gaussians.

    Args:
        means: `(B, 3)` world-space centres.
        covars6: `(B, 6)` packed blurred covariances `Σ + s sᵀ / 12`.
        sweep: `(B, 3)` displacement `s` of each Gaussian over the exposure (world units).
        viewmat, K, width, height, eps2d, near, far, backend: as in `rasterize`.

    Returns `sqrt(det(Σ2_blur - s2 s2ᵀ / 12) / det Σ2_blur)` of the screen-space covariances
    (with `eps2d`, through the rasteriser's Jacobian), `s2` the projected sweep; by the matrix
    determinant lemma that is `sqrt(1 - s2ᵀ Σ2_blur⁻¹ s2 / 12)`, in (0, 1].

    Differentiable in `covars6` and `sweep`. The screen-space map is held constant, so no
    gradient reaches `means`: the factor hardly depends on them, since the projected sweep and
    covariance scale together with depth.
    """
    impl = cpu_backend if resolve_backend(backend, means) == "cpu" else torch_backend
    return impl.blur_opacity_scale(means, covars6, sweep, viewmat, K, width, height, eps2d, near, far)


def blurred_opacities(
    opacities: Tensor,
    means: Tensor,
    covars6: Tensor,
    sweep: tuple[Tensor | None, Tensor],
    viewmat: Tensor,
    K: Tensor,
    width: int,
    height: int,
) -> Tensor:
    """`(N,)` opacities with the blurred Gaussians' scaled by `blur_opacity_scale`. `sweep` is
    `(idx (B,), sweeps (B, 3))`, or `(None, sweeps (N, 3))` for all N (`GaussiansAt.sweep`)."""
    idx, sweeps = sweep
    if idx is None:
        return opacities * blur_opacity_scale(means, covars6, sweeps, viewmat, K, width, height)
    scale = blur_opacity_scale(means[idx], covars6[idx], sweeps, viewmat, K, width, height)
    return opacities.index_put((idx,), opacities[idx] * scale)
