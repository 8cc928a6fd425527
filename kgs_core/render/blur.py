"""Motion blur as a splat's elongation, made mass-preserving.

The convolve form of the kinematic refinement (`model/kinematics.py: motion_blur_covariance`)
blurs a Gaussian that sweeps `s` during the exposure by adding the sweep's second moment to
its covariance, `Σ_blur = Σ + s sᵀ / 12`. On screen that widens the splat but keeps its peak
opacity, so its footprint (opacity times the 2D Gaussian's area) grows by
`sqrt(det Σ2_blur / det Σ2)`: a blurred splat would cover more than the Gaussian does over
the exposure. Physically the exposure averages the sharp splat along its path, which
conserves that footprint; `blur_opacity_scale` is the factor that restores it.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .covariance import unpack_covariance
from .torch_backend import camera_jacobian
from .types import EPS2D


def blur_opacity_scale(means: Tensor, covars6: Tensor, sweep: Tensor, viewmat: Tensor, K: Tensor, width: int,
                       height: int, eps2d: float = EPS2D, near: float = 0.01, far: float = 1e10) -> Tensor:
    """`(B,)` opacity factors for B blurred Gaussians.

    Args:
        means: `(B, 3)` world-space centres.
        covars6: `(B, 6)` packed blurred covariances `Σ + s sᵀ / 12`.
        sweep: `(B, 3)` displacement `s` of each Gaussian over the exposure (world units).
        viewmat, K, width, height, eps2d, near, far: as in `rasterize`.

    Returns `sqrt(det(Σ2_blur - s2 s2ᵀ / 12) / det Σ2_blur)` of the screen-space covariances
    (with `eps2d`), `s2` the projected sweep; by the matrix determinant lemma that is
    `sqrt(1 - s2ᵀ Σ2_blur⁻¹ s2 / 12)`, in (0, 1]. Differentiable in every input but the camera.
    """
    viewmat, K = viewmat.to(means.dtype), K.to(means.dtype)
    _, _, J = camera_jacobian(means, viewmat, K, width, height, near, far)
    M = J @ viewmat[:3, :3]  # world -> screen, (B, 2, 3)
    cov2d = M @ unpack_covariance(covars6) @ M.transpose(1, 2)
    a, b, c = cov2d[:, 0, 0] + eps2d, cov2d[:, 0, 1], cov2d[:, 1, 1] + eps2d
    s2 = (M @ sweep[:, :, None]).squeeze(-1)
    u, v = s2.unbind(-1)
    det = (a * c - b * b).clamp_min(1e-20)
    q = (c * u * u - 2 * b * u * v + a * v * v) / det  # s2ᵀ Σ2_blur⁻¹ s2
    # q / 12 < 1 exactly (Σ2_blur - s2 s2ᵀ/12 is positive definite); the clamp absorbs rounding.
    return (1 - q / 12).clamp_min(1e-6).sqrt()
