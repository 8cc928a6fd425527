"""Baking a run into plain per-time Gaussians: what every exporter, the server's splat streams
and the viewers start from.

`ExportSource` is a run opened for export: one LoD level, the edit layer applied, the frame
interval and whether the scene moves at all. `bake(source, t)` evaluates the deformation and the
kinematic covariance at time `t` and returns numpy arrays; `scales_quats_from_covars` fits a
baked covariance back to the scale + rotation form of the standard 3DGS files.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..edits import EditLayer, load_edits
from ..model.dynamic import KinematicsGS
from ..model.gaussians import GaussiansAt
from ..render.blur import blurred_opacities
from ..render.covariance import pack_covariance, quat_to_rotmat
from ..render.sh import C0
from ..run import LoadedRun, learned_blur, load_run
from ..train.camera_motion import nearest_camera_motion

if TYPE_CHECKING:
    from .web_frame import Similarity


@dataclass
class Baked:
    """Gaussians at one time, numpy, world (normalised scene) units."""

    means: np.ndarray  # (N, 3) float32
    covars: np.ndarray  # (N, 3, 3) float64 (kept in double for the exact scale/rotation fit)
    opacities: np.ndarray  # (N,) float32 in (0, 1)
    sh: np.ndarray  # (N, K, 3) float32, K = (degree + 1)^2
    dynamic: np.ndarray  # (N,) bool
    velocity: np.ndarray  # (N, 3) float32, scene units per unit time; zeros for static
    index: np.ndarray  # (N,) int64: index into the level's Gaussians
    # (N, 3) float32: each Gaussian's sweep over the exposure when it was baked with one (the
    # convolve form's blur; zeros otherwise). `render_baked` scales the swept ones' opacities
    # to keep each splat's 2D mass (render/blur.py); camera-independent files cannot, and
    # store the plain opacities.
    sweep: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.means)

    @property
    def rgb(self) -> np.ndarray:
        """View-independent colour `(N, 3)` in [0, 1] (the SH DC term)."""
        return np.clip(0.5 + C0 * self.sh[:, 0, :], 0.0, 1.0)


@dataclass
class ExportSource:
    run: LoadedRun
    lod: int
    model: KinematicsGS
    keep: np.ndarray  # (N,) bool: Gaussians surviving the edit layer
    dt: float  # one frame interval in normalised time
    static_only: bool  # a run trained without deformation (`--ablate deform`)
    frame: "Similarity | None" = None  # coordinates the baked Gaussians are written in (web_frame.py)

    @property
    def moves(self) -> bool:
        """Whether any kept Gaussian deforms: a static result needs one frame, not N copies."""
        if self.static_only:
            return False
        m = self.model
        dyn = m.dynamic.numpy() if m.decomposed else np.ones(len(m), dtype=bool)
        return bool((dyn & self.keep).any())

    @property
    def sh_degree(self) -> int:
        return self.model.config.sh_degree


def open_source(run: str | Path | LoadedRun, lod: int | None = None, edits: EditLayer | None = None) -> ExportSource:
    run = run if isinstance(run, LoadedRun) else load_run(run)
    lod = run.n_levels if lod is None else int(lod)
    model = run.level(lod)
    edits = load_edits(run.path) if edits is None else edits
    keep = edits.keep_mask(lod, model.params.means.detach().numpy())
    return ExportSource(run, lod, model, keep, float(run.info.get("dt", 1.0)), run.static_only)


@torch.no_grad()
def bake(source: ExportSource, t: float, exposure: float = 0.0) -> Baked:
    """The kept Gaussians at time `t`; `exposure` > 0 bakes the kinematic elongation of that
    shutter (as captured: with the camera's shake of the nearest training frame where the run
    kept one, `learned_blur`), 0 the sharp state."""
    m = source.model
    shake = nearest_camera_motion(learned_blur(source.run.info).get("camera_motion"), float(t)) if exposure > 0 else None
    g = m.at_static() if source.static_only else m.at(float(t), exposure=exposure, dt=source.dt, camera_motion=shake)
    baked = baked_from(g, source.keep)
    return source.frame.apply(baked) if source.frame is not None else baked


def baked_from(g: GaussiansAt, sel: np.ndarray, dynamic: np.ndarray | None = None) -> Baked:
    """The Gaussians `sel (N,) bool` of `g` as numpy; `dynamic (N,)` replaces `g.dynamic`."""
    s = torch.from_numpy(sel)
    velocity = g.velocity if g.velocity is not None else torch.zeros_like(g.means)
    sweep = torch.zeros_like(g.means)
    if g.sweep is not None:
        idx, swept = g.sweep
        sweep = swept if idx is None else sweep.index_put((idx,), swept)
    return Baked(
        means=g.means[s].numpy().astype(np.float32),
        covars=g.covars[s].double().numpy(),
        opacities=g.opacities[s].numpy().astype(np.float32),
        sh=g.sh[s].numpy().astype(np.float32),
        dynamic=(g.dynamic.numpy() if dynamic is None else dynamic)[sel].astype(bool),
        velocity=velocity[s].numpy().astype(np.float32),
        index=np.nonzero(sel)[0].astype(np.int64),
        sweep=sweep[s].numpy().astype(np.float32),
    )


def scales_quats_from_covars(covars: np.ndarray, min_scale: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Fits `Sigma = R diag(s)^2 R^T`: scales `(N, 3)` and unit quaternions `(N, 4)` wxyz with
    `w >= 0`. Exact up to float64 round-off (eigendecomposition), except that eigenvalues below
    `min_scale^2` (a degenerate, flat Gaussian) are raised to it."""
    cov = 0.5 * (covars + np.swapaxes(covars, -1, -2))
    evals, evecs = np.linalg.eigh(cov.astype(np.float64))
    scales = np.sqrt(np.maximum(evals, min_scale**2))
    # A proper rotation: flip one axis where the eigenvector frame is left-handed.
    flip = np.linalg.det(evecs) < 0
    evecs[flip, :, 0] *= -1
    return scales, rotmat_to_quat(evecs)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions `(N, 4)` wxyz (`w >= 0`) from rotation matrices `(N, 3, 3)`; branch per
    element on the largest diagonal term for accuracy near 180 degrees."""
    R = np.asarray(R, dtype=np.float64)
    n = len(R)
    q = np.empty((n, 4))
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = m00 + m11 + m22
    cases = np.stack([tr, m00, m11, m22], axis=1).argmax(1)
    for c in range(4):
        i = cases == c
        if not i.any():
            continue
        r = R[i]
        if c == 0:
            s = 2.0 * np.sqrt(1.0 + tr[i])
            q[i] = np.stack([0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s], 1)
        elif c == 1:
            s = 2.0 * np.sqrt(1.0 + m00[i] - m11[i] - m22[i])
            q[i] = np.stack([(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s], 1)
        elif c == 2:
            s = 2.0 * np.sqrt(1.0 + m11[i] - m00[i] - m22[i])
            q[i] = np.stack([(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s], 1)
        else:
            s = 2.0 * np.sqrt(1.0 + m22[i] - m00[i] - m11[i])
            q[i] = np.stack([(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1
    return q


def quat_to_rotmat_np(q: np.ndarray) -> np.ndarray:
    """`quat_to_rotmat` in float64 NumPy: rotation matrices `(..., 3, 3)` from wxyz quaternions."""
    quats = torch.from_numpy(np.asarray(q, dtype=np.float64))
    return quat_to_rotmat(quats.reshape(-1, 4)).numpy().reshape(tuple(quats.shape[:-1]) + (3, 3))


MAX_TIMES = 4096  # more exported times than this is a typo (one file or video frame each)


def parse_times(spec: str | None, default: list[float]) -> list[float]:
    """`--times`: `0.5` (one time), `0,0.25,0.5` (a list) or `0:1:30` (30 evenly spaced times,
    both ends included); None gives `default`. Times must lie in [0, 1], at most MAX_TIMES."""
    if spec is None or spec == "":
        return list(default)
    try:
        if ":" in spec:
            parts = spec.split(":")
            if len(parts) != 3:
                raise ValueError
            a, b, n = float(parts[0]), float(parts[1]), int(parts[2])
            if not 1 <= n <= MAX_TIMES:
                raise ValueError(f"--times: COUNT must be in 1..{MAX_TIMES}, got {n}")
            times = np.linspace(a, b, n).tolist()
        else:
            times = [float(s) for s in spec.split(",") if s.strip()]
    except ValueError as exc:
        if str(exc).startswith("--times"):
            raise
        raise ValueError(f"--times: expected T, T1,T2,... or START:STOP:COUNT, got {spec!r}") from None
    if not times or len(times) > MAX_TIMES:
        raise ValueError(f"--times: between 1 and {MAX_TIMES} times, got {len(times)} in {spec[:40]!r}")
    bad = [t for t in times if not (0.0 <= t <= 1.0) or not np.isfinite(t)]
    if bad:
        raise ValueError(f"--times: times must lie in [0, 1], got {bad[:3]}")
    return times


def render_baked(g: Baked, camera, sh_degree: int, background: np.ndarray | None = None, colors: np.ndarray | None = None):
    """Rasterises baked Gaussians (the edit layer already applied) from a `Camera`; returns
    `Rendered`. `colors (N, C)` replaces the SH colours (e.g. a static/dynamic overlay)."""
    from ..render import rasterize

    viewmat = torch.tensor(camera.viewmat, dtype=torch.float32)
    K = torch.tensor(camera.K, dtype=torch.float32)
    kw: dict = {}
    if colors is not None:
        kw["colors"] = torch.as_tensor(colors, dtype=torch.float32)
    else:
        kw["sh_coeffs"] = torch.from_numpy(g.sh)
        kw["sh_degree"] = sh_degree
    bg = np.zeros(kw["colors"].shape[1] if colors is not None else 3) if background is None else background
    means, covars = torch.from_numpy(g.means), pack_covariance(torch.from_numpy(g.covars.astype(np.float32)))
    opacities = torch.from_numpy(g.opacities)
    with torch.no_grad():
        if g.sweep is not None and g.sweep.any():  # as render_model: blurred splats keep their mass
            rows = torch.from_numpy(np.nonzero(g.sweep.any(1))[0])
            sweep = (rows, torch.from_numpy(g.sweep)[rows])
            opacities = blurred_opacities(opacities, means, covars, sweep, viewmat, K, camera.width, camera.height)
        return rasterize(
            means,
            opacities,
            viewmat,
            K,
            camera.width,
            camera.height,
            covars=covars,
            background=torch.as_tensor(bg, dtype=torch.float32),
            **kw,
        )
