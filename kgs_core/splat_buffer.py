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

A view-dependent colour buffer (`kind: "sh"`, sent once per LoD level when asked for) has the
same magic and header, `{"kind": "sh", "lod": …, "degree": d, "count": N, "bases": B}`, then
N × B × 3 float16: the SH coefficients after the DC term (B = (d+1)² - 1) of every Gaussian of
the level, by its index (the records' `index`), padded to a multiple of 4 bytes.

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
F16_MAX = 65504.0  # the largest float16: larger values are clipped to it, not sent as inf


def cov_scale(cov6: np.ndarray) -> float:
    """The median of the covariances' traces / 3, what `pack_buffer` divides them by (1.0 for
    none, or when it is not a positive number)."""
    if not len(cov6):
        return 1.0
    scale = float(np.median(cov6[:, [0, 3, 5]].sum(1) / 3))
    return scale if scale > 0 and np.isfinite(scale) else 1.0


def new_buffer(header: dict, n: int, velocity: bool, scale: float) -> tuple[bytearray, np.ndarray, np.ndarray | None]:
    """A zeroed buffer of the layout above for `n` splats, its header written: (the buffer, its
    `n` records, its `(n, 3)` float16 velocities or None), the last two writable views into it,
    so that a caller fills the splats in place and sends `bytes(buffer)`."""
    header = {**header, "count": n, "cov_scale": float(scale), "velocity": velocity}
    hj = json.dumps(header).encode()
    hj += b" " * (-len(hj) % 4)
    start = 8 + len(hj)
    vel_bytes = 6 * n if velocity else 0
    buf = bytearray(start + RECORD.itemsize * n + vel_bytes + (-vel_bytes % 4))
    buf[:4] = MAGIC
    struct.pack_into("<I", buf, 4, len(hj))
    buf[8:start] = hj
    rec = np.frombuffer(buf, dtype=RECORD, count=n, offset=start)
    vel = np.frombuffer(buf, dtype="<f2", count=3 * n, offset=start + RECORD.itemsize * n).reshape(n, 3) if velocity else None
    return buf, rec, vel


def pack_buffer(
    header: dict,
    means: np.ndarray,
    cov6: np.ndarray,
    rgba: np.ndarray,
    index: np.ndarray,
    velocity: np.ndarray | None = None,
    scale: float | None = None,
) -> bytes:
    """One buffer of the layout above from `means (N, 3)`, `cov6 (N, 6)` (packed upper
    triangles xx, xy, xz, yy, yz, zz), `rgba (N, 4) uint8`, `index (N,)` and optionally
    `velocity (N, 3)`; `scale` is the covariance unit (default `cov_scale(cov6)`)."""
    scale = cov_scale(cov6) if scale is None else float(scale)
    buf, rec, vel = new_buffer(header, len(means), velocity is not None, scale)
    rec["position"] = means
    rec["covariance"] = np.clip(cov6 / scale, -F16_MAX, F16_MAX)
    rec["rgba"] = rgba
    rec["index"] = index
    if vel is not None:
        vel[:] = np.clip(velocity, -F16_MAX, F16_MAX)
    return bytes(buf)


def pack_sh_buffer(header: dict, sh_rest: np.ndarray) -> bytes:
    """The view-dependent colour buffer of `sh_rest (N, B, 3)` (layout above)."""
    n, bases = sh_rest.shape[:2]
    hj = json.dumps({**header, "kind": "sh", "count": int(n), "bases": int(bases)}).encode()
    hj += b" " * (-len(hj) % 4)
    body = np.clip(sh_rest, -F16_MAX, F16_MAX).astype("<f2").tobytes()
    return MAGIC + struct.pack("<I", len(hj)) + hj + body + b"\0" * (-len(body) % 4)


def unpack_buffer(data: bytes) -> tuple[dict, np.ndarray, np.ndarray | None]:
    """(header, records, velocity or None): the reference reader of the layout above."""
    if data[:4] != MAGIC:
        raise ValueError("not a KGS1 splat buffer")
    (h,) = struct.unpack_from("<I", data, 4)
    header = json.loads(data[8 : 8 + h])
    n = header["count"]
    rec = np.frombuffer(data, dtype=RECORD, count=n, offset=8 + h)
    vel = None
    if header["velocity"]:
        vel = np.frombuffer(data, dtype="<f2", count=3 * n, offset=8 + h + 32 * n).reshape(n, 3)
    return header, rec, vel


def rgba_of(sh: torch.Tensor, opacities: torch.Tensor) -> np.ndarray:
    rgb = (0.5 + C0 * sh[:, 0, :]).clamp(0, 1)
    return (torch.cat([rgb, opacities[:, None]], 1) * 255 + 0.5).to(torch.uint8).numpy()
