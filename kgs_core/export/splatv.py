"""The splaTV `.splatv` container (antimatter15/splaTV), a 4D splat file for its web player.

Layout (little-endian): `uint32 magic = 0x674b`, `uint32 n` (length of the JSON header),
n bytes of JSON `[{"type": "splat", "size": bytes, "texwidth": 4096, "texheight": H,
"cameras": [...]}]`, then `size` bytes of texture: 16 uint32 words a splat, 1024 splats a row:

| word  | content                                                    |
| ----- | ---------------------------------------------------------- |
| 0-2   | position x, y, z (float32)                                 |
| 3-4   | rotation w, x | y, z (two half floats each)                |
| 5-6   | scale 0, 1 | scale 2, 0 (half, linear)                      |
| 7     | R, G, B, A (uint8)                                         |
| 8-12  | motion: 9 half floats (linear xyz, quadratic xyz, cubic xyz) |
| 13-14 | omega: 4 half floats (rotation velocity, added to the quaternion) |
| 15    | trbf centre, trbf scale (half)                             |

The player evaluates at time `t`: `dt = t - centre`, position `p + m1 dt + m2 dt^2 + m3 dt^3`,
rotation `normalize(q + omega dt)`, opacity `A exp(-(dt / scale)^2)`. Our trajectories come from a
deformation field, so we *fit* that model per Gaussian (least squares over sampled times) and
report how far the fit is from the real trajectories (`SplatvFit`). Scales are constant in this
format: time-varying scale (the deformation's `ds`, kinematic elongation) is averaged, and so
is a time-varying opacity (`model.time_opacity`) of the Gaussians present at every time.
"""

from __future__ import annotations

import itertools
import json
import math
import struct
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..io import atomic_write_bytes
from ..progress import progress_bar
from .bake import ExportSource, bake, quat_to_rotmat_np, rotmat_to_quat

SPLATV_MAGIC = 0x674B
SPLATS_PER_ROW = 1024
TEX_WIDTH = 4 * SPLATS_PER_ROW
TIME_CENTRE = 0.5
TRBF_SCALE = 100.0  # persistent Gaussians: exp(-(0.5 / 100)^2) = 0.99998 at the ends
HALF_MAX = 65504.0
_PERMS = list(itertools.permutations(range(3)))


@dataclass
class SplatvFit:
    gaussians: int
    dynamic: int
    fit_times: int
    check_times: int
    position_rms: float  # scene units, over dynamic Gaussians and check times
    position_max: float
    position_rms_rel: float  # relative to the scene extent (bounding-box diagonal)
    covariance_rel_mean: float  # |Sigma_fit - Sigma| / |Sigma| (Frobenius), mean over dynamic
    covariance_rel_max: float

    def to_dict(self) -> dict:
        return asdict(self)


def _half(x: np.ndarray) -> np.ndarray:
    return np.clip(x, -HALF_MAX, HALF_MAX).astype(np.float16)


def _pack_half2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return _half(a).view(np.uint16).astype(np.uint32) | (_half(b).view(np.uint16).astype(np.uint32) << 16)


def _aligned_rotations(covars: np.ndarray, ref_axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigen-frames of `covars (N, 3, 3)` with columns permuted and signed to match `ref_axes`
    (so the quaternion varies continuously in time); returns (R (N, 3, 3), variances (N, 3))."""
    evals, evecs = np.linalg.eigh(covars)
    overlap = np.abs(np.einsum("nij,nik->njk", ref_axes, evecs))  # (N, ref col, new col)
    scores = np.stack([overlap[:, [0, 1, 2], list(p)].sum(1) for p in _PERMS], 1)
    best = scores.argmax(1)
    perm = np.asarray(_PERMS)[best]  # (N, 3)
    R = np.take_along_axis(evecs, perm[:, None, :], axis=2)
    var = np.take_along_axis(evals, perm, axis=1)
    sign = np.sign(np.einsum("nij,nij->nj", ref_axes, R))
    sign[sign == 0] = 1
    R = R * sign[:, None, :]
    return R, np.maximum(var, 0.0)


def fit_splatv(source: ExportSource, fit_times: list[float], exposure: float = 0.0, progress: bool = True) -> tuple[np.ndarray, SplatvFit]:
    """Fits the splaTV motion model; returns (texture words `(N, 16)` uint32, fit report)."""
    times = np.asarray(sorted(set(fit_times)), dtype=np.float64)
    if len(times) < 4 and source.moves:
        raise ValueError("splatv: need at least 4 distinct times to fit the cubic motion model")
    ref = bake(source, TIME_CENTRE, exposure)
    n = len(ref)
    ref_var, ref_axes = np.linalg.eigh(ref.covars)
    ref_axes[np.linalg.det(ref_axes) < 0, :, 0] *= -1
    dyn = ref.dynamic.copy() if source.moves else np.zeros(n, dtype=bool)

    means = np.empty((len(times), n, 3))
    quats = np.empty((len(times), n, 4))
    variances = np.empty((len(times), n, 3))
    opacities = np.empty((len(times), n))
    for k, t in enumerate(progress_bar(times, desc="splatv: sample trajectories", stage="sample trajectories", unit="t", show=progress)):
        g = bake(source, float(t), exposure) if source.moves else ref
        R, var = _aligned_rotations(g.covars, ref_axes)
        means[k], variances[k], quats[k], opacities[k] = g.means, var, rotmat_to_quat(R), g.opacities
    q_ref = rotmat_to_quat(ref_axes)
    hemisphere = np.sign(np.einsum("tni,ni->tn", quats, q_ref))  # q and -q are one rotation
    hemisphere[hemisphere == 0] = 1
    quats *= hemisphere[..., None]

    dt = times - TIME_CENTRE
    V = np.stack([np.ones_like(dt), dt, dt**2, dt**3], 1)  # (T, 4)
    pos_coef = np.linalg.lstsq(V, means.reshape(len(times), -1), rcond=None)[0].reshape(4, n, 3)
    Vq = V[:, :2]
    rot_coef = np.linalg.lstsq(Vq, quats.reshape(len(times), -1), rcond=None)[0].reshape(2, n, 4)
    scales = np.sqrt(variances.mean(0))
    # Static Gaussians: exactly their (only) state.
    pos_coef[1:, ~dyn] = 0.0
    pos_coef[0, ~dyn] = ref.means[~dyn]
    rot_coef[1, ~dyn] = 0.0
    rot_coef[0, ~dyn] = q_ref[~dyn]
    scales[~dyn] = np.sqrt(np.maximum(ref_var[~dyn], 0.0))

    # Gaussians present for part of the clip (`KinematicsGS.lifespan`): the player's own temporal
    # opacity, A exp(-(dt / s)^2) with s = sqrt(2) x width, and A the opacity before that factor
    # (the reference bake at TIME_CENTRE has it applied).
    life = source.model.lifespan[torch.from_numpy(source.keep)].numpy().astype(np.float64)
    bounded = np.isfinite(life[:, 1])
    opacity = ref.opacities.astype(np.float64).copy()
    if source.model.time_opacity is not None:  # time-varying opacity is averaged, as scale is
        opacity[~bounded] = opacities.mean(0)[~bounded]
    opacity[bounded] = source.model.params.opacities.detach()[torch.from_numpy(source.keep)].numpy()[bounded]
    centre, trbf = np.full(n, TIME_CENTRE), np.full(n, TRBF_SCALE)
    centre[bounded], trbf[bounded] = life[bounded, 0], np.sqrt(2.0) * life[bounded, 1]
    # The player's polynomials are in time from each Gaussian's own centre: re-expand the fitted
    # ones (in time from TIME_CENTRE) about it, exactly (binomial shift).
    delta = centre - TIME_CENTRE  # (N,)
    shifted = np.zeros_like(pos_coef)
    for j in range(4):
        for k in range(j, 4):
            shifted[j] += math.comb(k, j) * (delta ** (k - j))[:, None] * pos_coef[k]
    pos_coef = shifted
    rot_coef[0] = rot_coef[0] + delta[:, None] * rot_coef[1]

    words = np.zeros((n, 16), dtype=np.uint32)
    words[:, 0:3] = pos_coef[0].astype(np.float32).view(np.uint32)
    words[:, 3] = _pack_half2(rot_coef[0][:, 0], rot_coef[0][:, 1])
    words[:, 4] = _pack_half2(rot_coef[0][:, 2], rot_coef[0][:, 3])
    words[:, 5] = _pack_half2(scales[:, 0], scales[:, 1])
    words[:, 6] = _pack_half2(scales[:, 2], np.zeros(n))
    rgba = np.clip(np.round(np.concatenate([ref.rgb, opacity[:, None]], 1) * 255), 0, 255).astype(np.uint8)
    words[:, 7] = rgba.view(np.uint32)[:, 0]
    motion = np.concatenate([pos_coef[1], pos_coef[2], pos_coef[3]], 1)  # (N, 9)
    motion = np.concatenate([motion, np.zeros((n, 1))], 1)
    for w in range(5):
        words[:, 8 + w] = _pack_half2(motion[:, 2 * w], motion[:, 2 * w + 1])
    words[:, 13] = _pack_half2(rot_coef[1][:, 0], rot_coef[1][:, 1])
    words[:, 14] = _pack_half2(rot_coef[1][:, 2], rot_coef[1][:, 3])
    words[:, 15] = _pack_half2(centre, trbf)

    # Check the fit, as the player decodes it, at times between the fitted ones as well.
    check = np.linspace(times[0], times[-1], 2 * len(times) - 1) if len(times) > 1 else times
    decoded = decode_splatv_words(words)
    extent = float(np.linalg.norm(ref.means.max(0) - ref.means.min(0))) if n else 1.0
    pos_err, cov_err = [], []
    if dyn.any():
        for t in progress_bar(check, desc="splatv: check fit", stage="check the fit", unit="t", show=progress):
            g = bake(source, float(t), exposure)
            p, cov, _ = evaluate_splatv(decoded, float(t))
            pos_err.append(np.linalg.norm(p[dyn] - g.means[dyn], axis=1))
            cov_err.append(
                np.linalg.norm(cov[dyn] - g.covars[dyn], axis=(1, 2)) / np.maximum(np.linalg.norm(g.covars[dyn], axis=(1, 2)), 1e-30)
            )
    pe = np.concatenate(pos_err) if pos_err else np.zeros(1)
    ce = np.concatenate(cov_err) if cov_err else np.zeros(1)
    report = SplatvFit(
        gaussians=n,
        dynamic=int(dyn.sum()),
        fit_times=len(times),
        check_times=len(check),
        position_rms=float(np.sqrt((pe**2).mean())),
        position_max=float(pe.max()),
        position_rms_rel=float(np.sqrt((pe**2).mean()) / max(extent, 1e-12)),
        covariance_rel_mean=float(ce.mean()),
        covariance_rel_max=float(ce.max()),
    )
    return words, report


def splatv_bytes(words: np.ndarray, cameras: list[dict] | None = None) -> bytes:
    n = len(words)
    rows = max(1, -(-n // SPLATS_PER_ROW))
    tex = np.zeros((rows * SPLATS_PER_ROW, 16), dtype=np.uint32)
    tex[:n] = words
    header = json.dumps(
        [{"type": "splat", "size": tex.nbytes, "texwidth": TEX_WIDTH, "texheight": rows, "count": n, "cameras": cameras or []}]
    ).encode()
    return struct.pack("<II", SPLATV_MAGIC, len(header)) + header + tex.astype("<u4").tobytes()


def read_splatv(data: bytes) -> tuple[list[dict], np.ndarray]:
    """(header chunks, texture words `(rows * 1024, 16)` uint32) of a `.splatv` file."""
    if len(data) < 8:
        raise ValueError("splatv: file shorter than its 8-byte preamble")
    magic, n = struct.unpack_from("<II", data, 0)
    if magic != SPLATV_MAGIC:
        raise ValueError(f"splatv: bad magic {magic:#x} (expected {SPLATV_MAGIC:#x})")
    header = json.loads(data[8 : 8 + n])
    chunk = header[0]
    tex = np.frombuffer(data, dtype="<u4", count=chunk["size"] // 4, offset=8 + n).reshape(-1, 16)
    return header, tex


def decode_splatv_words(words: np.ndarray) -> dict:
    """The fields of texture words `(N, 16)`, decoded the way the splaTV shader does."""

    def halves(w):
        w = w.astype(np.uint32)
        lo = (w & 0xFFFF).astype(np.uint16).view(np.float16).astype(np.float64)
        hi = (w >> 16).astype(np.uint16).view(np.float16).astype(np.float64)
        return lo, hi

    pos = words[:, 0:3].copy().view(np.float32).astype(np.float64)
    r0, r1 = halves(words[:, 3])
    r2, r3 = halves(words[:, 4])
    s0, s1 = halves(words[:, 5])
    s2, _ = halves(words[:, 6])
    m = np.stack([v for w in range(8, 13) for v in halves(words[:, w])], 1)[:, :9]
    o0, o1 = halves(words[:, 13])
    o2, o3 = halves(words[:, 14])
    tc, ts = halves(words[:, 15])
    rgba = words[:, 7].copy().view(np.uint8).reshape(-1, 4)
    return {
        "position": pos,
        "rotation": np.stack([r0, r1, r2, r3], 1),
        "scale": np.stack([s0, s1, s2], 1),
        "rgba": rgba,
        "motion": m,
        "omega": np.stack([o0, o1, o2, o3], 1),
        "trbf_center": tc,
        "trbf_scale": ts,
    }


def evaluate_splatv(d: dict, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position `(N, 3)`, covariance `(N, 3, 3)` and opacity `(N,)` at time `t` (the player's model)."""
    dt = t - d["trbf_center"]
    m = d["motion"]
    p = d["position"] + m[:, 0:3] * dt[:, None] + m[:, 3:6] * (dt**2)[:, None] + m[:, 6:9] * (dt**3)[:, None]
    q = d["rotation"] + d["omega"] * dt[:, None]
    R = quat_to_rotmat_np(q)
    M = R * d["scale"][:, None, :]
    opacity = d["rgba"][:, 3] / 255.0 * np.exp(-((dt / d["trbf_scale"]) ** 2))
    return p, M @ np.swapaxes(M, 1, 2), opacity


DISPLAY_WIDTH = 1280  # splaTV's cameras are sized for a window about this wide


def splatv_cameras(frames, limit: int = 10) -> list[dict]:
    """Cameras in the splaTV/3DGS `cameras.json` form (centre, camera-to-world rotation, focal).

    splaTV reads `fx`/`fy` in pixels of its window (`innerWidth`) and ignores the camera's own
    size, so the training camera's focal length in pixels of a 128 px frame drew a 158° field
    of view there and the scene tiny. Each camera is written scaled up to a display-sized
    image (DISPLAY_WIDTH wide, the same field of view and aspect), never scaled down."""
    if not frames:
        return []
    step = max(1, len(frames) // limit)
    out = []
    for i, f in enumerate(frames[::step][:limit]):
        R = f.camera.viewmat[:3, :3]
        k = max(1.0, DISPLAY_WIDTH / f.camera.width)
        out.append(
            {
                "id": i,
                "img_name": f.id,
                "width": round(f.camera.width * k),
                "height": round(f.camera.height * k),
                "position": f.camera.center.tolist(),
                "rotation": R.T.tolist(),
                "fx": float(f.camera.K[0, 0]) * k,
                "fy": float(f.camera.K[1, 1]) * k,
            }
        )
    return out


def write_splatv(path: str | Path, words: np.ndarray, cameras: list[dict] | None = None) -> Path:
    return atomic_write_bytes(path, splatv_bytes(words, cameras))
