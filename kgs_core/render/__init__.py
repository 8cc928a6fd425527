"""Differentiable Gaussian rasteriser: `rasterize` is the entry point."""

from .camera import intrinsics, look_at
from .rasterize import packed_covariance, rasterize, resolve_backend
from .types import Projection, Rendered

__all__ = ["rasterize", "packed_covariance", "resolve_backend", "Rendered", "Projection", "look_at", "intrinsics"]
