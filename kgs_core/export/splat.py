"""The antimatter15 `.splat` layout: 32 bytes a splat, little-endian, no header:
position 3 x float32, scale 3 x float32 (linear), RGBA 4 x uint8 (colour = SH DC, alpha =
opacity), rotation 4 x uint8 (wxyz, `q * 128 + 128`). Sorted by `volume x opacity`, largest first,
as the reference converter does (viewers stream and draw the important splats first)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io import atomic_write_bytes
from .bake import Baked, scales_quats_from_covars

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def splat_records(g: Baked) -> np.ndarray:
    scales, quats = scales_quats_from_covars(g.covars)
    order = np.argsort(-(scales.prod(1) * g.opacities), kind="stable")
    rec = np.empty(len(g), dtype=SPLAT_DTYPE)
    rec["position"] = g.means[order]
    rec["scale"] = scales[order]
    rgba = np.concatenate([g.rgb, g.opacities[:, None]], axis=1)[order]
    rec["rgba"] = np.clip(np.round(rgba * 255), 0, 255).astype(np.uint8)
    rec["rot"] = np.clip(np.round(quats[order] * 128 + 128), 0, 255).astype(np.uint8)
    return rec


def write_splat(path: str | Path, g: Baked) -> Path:
    return atomic_write_bytes(path, splat_records(g).tobytes())


def read_splat(data: bytes) -> np.ndarray:
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(f".splat data of {len(data)} bytes is not a whole number of 32-byte records")
    return np.frombuffer(data, dtype=SPLAT_DTYPE)
