"""Standard 3DGS `.ply` (the layout of the original implementation, read by every splat viewer):
`x y z nx ny nz f_dc_0..2 f_rest_0.. opacity scale_0..2 rot_0..3`, with opacity as a logit,
log scales, wxyz quaternions and `f_rest` stored channel-major (all R coefficients, then G, B)."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from plyfile import PlyData, PlyElement

from ..io import atomic_write_bytes
from .bake import Baked, scales_quats_from_covars


def ply_bytes(g: Baked) -> bytes:
    n, k, _ = g.sh.shape
    scales, quats = scales_quats_from_covars(g.covars)
    o = np.clip(g.opacities.astype(np.float64), 1e-7, 1 - 1e-7)
    rest = np.ascontiguousarray(g.sh[:, 1:, :].transpose(0, 2, 1)).reshape(n, 3 * (k - 1))
    names = (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(rest.shape[1])]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )
    cols = np.concatenate(
        [g.means, np.zeros((n, 3)), g.sh[:, 0, :], rest, np.log(o / (1 - o))[:, None], np.log(scales), quats], axis=1
    ).astype(np.float32)
    arr = np.empty(n, dtype=[(name, "f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = cols[:, i]
    buf = io.BytesIO()
    PlyData([PlyElement.describe(arr, "vertex")], text=False).write(buf)
    return buf.getvalue()


def write_ply(path: str | Path, g: Baked) -> Path:
    return atomic_write_bytes(path, ply_bytes(g))
