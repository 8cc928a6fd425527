"""Photometric losses: the fused C++ SSIM against the PyTorch reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kgs_core.losses import coarse_l1, gradient_l1, l1, photometric_loss, ssim, ssim_reference
from kgs_core.render import _ext

pytestmark = pytest.mark.skipif(not _ext.compiler_available(), reason="no C++ compiler")


@pytest.mark.parametrize("shape", [(64, 64, 3), (37, 53, 3), (11, 20, 1), (30, 12, 4)])
def test_fused_ssim_matches_reference(shape):
    g = torch.Generator().manual_seed(sum(shape))
    ref = torch.rand(shape, generator=g)
    img = (ref + 0.2 * torch.randn(shape, generator=g)).clamp(0, 1).requires_grad_(True)
    fused = ssim(img, ref)
    (g_fused,) = torch.autograd.grad(fused, img)
    expected = ssim_reference(img, ref)
    (g_ref,) = torch.autograd.grad(expected, img)
    assert fused.item() == pytest.approx(expected.item(), abs=1e-6)
    assert float((g_fused - g_ref).abs().max()) <= 1e-5 * float(g_ref.abs().max())


def test_fused_ssim_identical_images_is_one():
    img = torch.rand(32, 32, 3)
    assert ssim(img.clone().requires_grad_(True), img).item() == pytest.approx(1.0, abs=1e-6)


def test_fused_ssim_gradcheck_float64():
    g = torch.Generator().manual_seed(3)
    img = torch.rand(9, 10, 2, dtype=torch.float64, generator=g).requires_grad_(True)
    ref = torch.rand(9, 10, 2, dtype=torch.float64, generator=g)
    assert torch.autograd.gradcheck(lambda x: ssim(x, ref, window_size=5), (img,))


def test_ssim_with_a_differentiable_reference_uses_the_reference_path():
    a = torch.rand(16, 16, 3, requires_grad=True)
    b = torch.rand(16, 16, 3, requires_grad=True)
    ssim(a, b).backward()
    assert b.grad is not None and float(b.grad.abs().sum()) > 0


def test_photometric_loss_gradient_flows_through_fused_ssim():
    ref = torch.rand(24, 24, 3)
    img = torch.rand(24, 24, 3, requires_grad=True)
    photometric_loss(img, ref, lambda_dssim=1.0).backward()
    assert torch.isfinite(img.grad).all() and float(img.grad.abs().sum()) > 0


def test_coarse_l1_still_sees_how_far_a_displaced_object_is():
    """A 4 px square drawn 6 or 12 px from where the frame has it: full-resolution L1 is the same
    for both (no overlap either way, so it has no gradient towards the right place); the 8 px
    pooled term is lower for the nearer one."""

    def square(x0: int) -> torch.Tensor:
        img = torch.zeros(32, 48, 3)
        img[12:16, x0 : x0 + 4] = 1.0
        return img

    frame = square(8)
    near, far = square(14), square(20)
    assert l1(near, frame) == pytest.approx(float(l1(far, frame)))
    assert coarse_l1(near, frame, 8) < coarse_l1(far, frame, 8)


def test_gradient_l1_is_the_mean_difference_of_neighbouring_pixels_and_weighs_a_residual_by_its_frequency():
    """gradient_l1 = (mean |Δx(img − ref)| + mean |Δy(img − ref)|) / 2 with Δ the difference of
    neighbouring pixels: blind to a constant offset, and of a sinusoidal residual of period P it
    takes a share of about 2 sin(π/P) / 2 (against l1's 1): the finer the residual, the larger its weight."""
    g = torch.Generator().manual_seed(0)
    ref = torch.rand(9, 7, 3, generator=g)
    img = torch.rand(9, 7, 3, generator=g)
    r = (img - ref).numpy()
    expected = 0.5 * (abs(r[:, 1:] - r[:, :-1]).mean() + abs(r[1:] - r[:-1]).mean())
    assert gradient_l1(img, ref).item() == pytest.approx(float(expected), rel=1e-6)
    assert gradient_l1(ref + 0.3, ref).item() == pytest.approx(0.0, abs=1e-7)
    x = torch.arange(256, dtype=torch.float64)
    ratios = []
    for period in (8.0, 16.0, 64.0):
        residual = (0.1 * torch.sin(2 * torch.pi * x / period))[None, :, None].expand(64, 256, 1)
        ratios.append((gradient_l1(residual, torch.zeros_like(residual)) / l1(residual, torch.zeros_like(residual))).item())
    assert ratios[0] > ratios[1] > ratios[2]
    # Along x mean |Δ sin| / mean |sin| = 2 sin(π/P) where the period spans many pixels; along y nothing changes.
    assert ratios[2] == pytest.approx(0.5 * 2 * np.sin(np.pi / 64), rel=0.02)
