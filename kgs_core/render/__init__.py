"""Differentiable Gaussian rasteriser: `rasterize` is the entry point."""

from .camera import intrinsics, look_at
from .rasterize import rasterize, resolve_backend
from .types import Projection, Rendered

__all__ = ["rasterize", "resolve_backend", "Rendered", "Projection", "look_at", "intrinsics"]
