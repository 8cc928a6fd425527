"""Photometric losses and image metrics on `(H, W, C)` images in [0, 1]."""

from __future__ import annotations

import functools
import math

import torch
import torch.nn.functional as F
from torch import Tensor


@functools.lru_cache(maxsize=8)
def _gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return (g / g.sum()).to(dtype)


def _blur(x: Tensor, window: Tensor) -> Tensor:
    """Separable 'valid' Gaussian blur of `(1, C, H, W)`."""
    c = x.shape[1]
    k = window.numel()
    x = F.conv2d(x, window.view(1, 1, 1, k).expand(c, 1, 1, k), groups=c)
    return F.conv2d(x, window.view(1, 1, k, 1).expand(c, 1, k, 1), groups=c)


class _FusedSSIM(torch.autograd.Function):
    """SSIM through the C++ extension (kgs_core/render/csrc/ssim.cpp): one pass for the five
    blurred maps and one for the gradient, instead of ten depthwise convolutions and their
    backward (45 ms -> a few ms per 256x256 image on two cores)."""

    @staticmethod
    def forward(ctx, img, ref, window):
        from .render import _ext

        value, maps = _ext.load().ssim_forward(img, ref, window)
        ctx.save_for_backward(img, ref, window, maps)
        return value

    @staticmethod
    def backward(ctx, grad):
        from .render import _ext

        img, ref, window, maps = ctx.saved_tensors
        return _ext.load().ssim_backward(img, ref, window, maps, float(grad)), None, None


def ssim(img: Tensor, ref: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """Mean SSIM (Wang et al. 2004) with an 11-tap Gaussian window over valid pixels.

    Uses the fused C++ kernel when it can (CPU tensors, `ref` a constant), else
    `ssim_reference`; both compute the same value (tested)."""
    if img.shape != ref.shape:
        raise ValueError(f"ssim: shapes differ {tuple(img.shape)} vs {tuple(ref.shape)}")
    from .render import _ext

    if img.dim() == 3 and not ref.requires_grad and _ext.usable_for(img):
        size = min(window_size, img.shape[0], img.shape[1])
        w = _gaussian_window(size, sigma, img.dtype)
        return _FusedSSIM.apply(img.contiguous(), ref.detach().to(img.dtype).contiguous(), w)
    return ssim_reference(img, ref, window_size, sigma)


def ssim_reference(img: Tensor, ref: Tensor, window_size: int = 11, sigma: float = 1.5) -> Tensor:
    """SSIM in plain PyTorch (separable depthwise convolutions): any device, any autograd."""
    if img.shape != ref.shape:
        raise ValueError(f"ssim: shapes differ {tuple(img.shape)} vs {tuple(ref.shape)}")
    x = img.permute(2, 0, 1).unsqueeze(0)
    y = ref.permute(2, 0, 1).unsqueeze(0)
    size = min(window_size, x.shape[-1], x.shape[-2])
    w = _gaussian_window(size, sigma, x.dtype)
    mu_x, mu_y = _blur(x, w), _blur(y, w)
    sxx = _blur(x * x, w) - mu_x**2
    syy = _blur(y * y, w) - mu_y**2
    sxy = _blur(x * y, w) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2)
    return (num / den).mean()


def l1(img: Tensor, ref: Tensor) -> Tensor:
    return (img - ref).abs().mean()


def photometric_loss(img: Tensor, ref: Tensor, lambda_dssim: float = 0.2) -> Tensor:
    """`(1 - lambda) L1 + lambda (1 - SSIM)` as in 3DGS and the paper."""
    return (1 - lambda_dssim) * l1(img, ref) + lambda_dssim * (1 - ssim(img, ref))


def gradient_l1(img: Tensor, ref: Tensor) -> Tensor:
    """L1 between the horizontal and vertical finite differences of `(H, W, C)` images. Blur
    damps a sharp detail's share of the plain L1, so fitting blurry frames through a blur model
    learns it slowly; differences weigh a residual by its frequency, giving the detail its share back."""
    dx = (img[:, 1:] - img[:, :-1]) - (ref[:, 1:] - ref[:, :-1])
    dy = (img[1:] - img[:-1]) - (ref[1:] - ref[:-1])
    return 0.5 * (dx.abs().mean() + dy.abs().mean())


def coarse_l1(img: Tensor, ref: Tensor, factor: int) -> Tensor:
    """L1 between `(H, W, C)` images average-pooled by `factor`: a rendered object displaced from
    its image by up to about `factor` pixels still overlaps it there, so the loss keeps a
    gradient that pulls it back (at full resolution it has none once they stop overlapping)."""
    a = F.avg_pool2d(img.permute(2, 0, 1)[None], factor, ceil_mode=True)
    b = F.avg_pool2d(ref.permute(2, 0, 1)[None], factor, ceil_mode=True)
    return (a - b).abs().mean()


def psnr(img: Tensor, ref: Tensor, mask: Tensor | None = None) -> float:
    """PSNR in dB for images in [0, 1]; `mask (H, W)` restricts it to selected pixels."""
    err = (img.detach().clamp(0, 1) - ref.detach()) ** 2
    if mask is not None:
        m = mask.to(err.dtype).unsqueeze(-1).expand_as(err)
        if m.sum() == 0:
            return float("nan")
        mse = float((err * m).sum() / m.sum())
    else:
        mse = float(err.mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
