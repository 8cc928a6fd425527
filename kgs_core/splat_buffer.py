"""The binary splat buffer the viewers draw: one WebSocket binary message, little-endian.

Layout:
- bytes 0-3: `KGS1`.
- bytes 4-7: uint32 H, the length of the JSON header (padded with spaces to a multiple of 4).
- bytes 8 .. 8+H: the header, `{"kind": "static" | "dynamic", "count": N, "t": …, "lod": …,
  "cov_scale": s, "velocity": bool, "seq": …}`.
- then N records of 32 bytes (`RECORD`): position 3 × float32; covariance (xx, xy, xz, yy, yz,
  zz) 6 × float16 in units of `cov_scale`; RGBA 4 × uint8 (SH DC colour, opacity); index uint32
  (the Gaussian's id within the LoD level, for selection and edits).
- then, if `velocity`: N × 3 float16 velocities (scene units per unit time), padded to a
  multiple of 4 bytes.

Covariances are divided by `cov_scale` (the median of their traces / 3) so that float16 keeps
its precision for small Gaussians. `unpack_buffer` is the reference reader; the browser's is
`frontend/js/buffers.js`.
"""

from __future__ import annotations

import json
import struct

import numpy as np
import torch

from .render.sh import C0

MAGIC = b"KGS1"
RECORD = np.dtype([("position", "<f4", 3), ("covariance", "<f2", 6), ("rgba", "u1", 4), ("index", "<u4")])
assert RECORD.itemsize == 32
TRIU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


def pack_buffer(header: dict, means: np.ndarray, covars: np.ndarray, rgba: np.ndarray, index: np.ndarray,
                velocity: np.ndarray | None = None) -> bytes:
    n = len(means)
    cov6 = covars[:, TRIU[0], TRIU[1]] if n else np.zeros((0, 6))
    scale = float(np.median(cov6[:, [0, 3, 5]].sum(1) / 3)) if n else 1.0
    scale = scale if scale > 0 and np.isfinite(scale) else 1.0
    rec = np.empty(n, dtype=RECORD)
    rec["position"] = means
    rec["covariance"] = np.clip(cov6 / scale, -65504, 65504)
    rec["rgba"] = rgba
    rec["index"] = index
    header = {**header, "count": n, "cov_scale": scale, "velocity": velocity is not None}
    hj = json.dumps(header).encode()
    hj += b" " * (-len(hj) % 4)
    parts = [MAGIC, struct.pack("<I", len(hj)), hj, rec.tobytes()]
    if velocity is not None:
        v = np.clip(velocity, -65504, 65504).astype("<f2").tobytes()
        parts.append(v + b"\0" * (-len(v) % 4))
    return b"".join(parts)


def unpack_buffer(data: bytes) -> tuple[dict, np.ndarray, np.ndarray | None]:
    """(header, records, velocity or None): the reference reader of the layout above."""
    if data[:4] != MAGIC:
        raise ValueError("not a KGS1 splat buffer")
    (h,) = struct.unpack_from("<I", data, 4)
    header = json.loads(data[8:8 + h])
    n = header["count"]
    rec = np.frombuffer(data, dtype=RECORD, count=n, offset=8 + h)
    vel = None
    if header["velocity"]:
        vel = np.frombuffer(data, dtype="<f2", count=3 * n, offset=8 + h + 32 * n).reshape(n, 3)
    return header, rec, vel


def rgba_of(sh: torch.Tensor, opacities: torch.Tensor) -> np.ndarray:
    rgb = (0.5 + C0 * sh[:, 0, :]).clamp(0, 1)
    return (torch.cat([rgb, opacities[:, None]], 1) * 255 + 0.5).to(torch.uint8).numpy()
