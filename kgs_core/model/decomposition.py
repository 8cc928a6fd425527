"""The static/dynamic decomposition by the temporal variance K of the field's offsets, as methods of
`KinematicsGS` (a mixin), and the statistics read off it (τ by Otsu, counts, a histogram)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ..render.covariance import normalize_quats
from .kinematics import quat_multiply, rotvec_to_quat

if TYPE_CHECKING:
    from .dynamic import KinematicsGS


class Decomposition:
    """K, the decomposition and what it does to the canonical Gaussians (`KinematicsGS`'s `K`,
    `dynamic`, `decomposed`)."""

    @torch.no_grad()
    def compute_K(self, chunk: int = 8192) -> Tensor:
        """K_i = mean_t |dx_t - mean_t dx_t|^2 over `K_times` evenly spaced times, from the
        deformation field itself (no time noise, no coarse-to-fine averaging)."""
        T = self.config.K_times
        times = torch.linspace(0, 1, T)
        means = self.params.means.detach()
        out = torch.empty(len(means))
        for s in range(0, len(means), chunk):
            x = means[s : s + chunk]
            offs = self.deform.at_times(x, [torch.full((len(x),), float(t)) for t in times])
            dx = torch.stack([o.dx for o in offs])  # (T, n, 3)
            out[s : s + chunk] = ((dx - dx.mean(0)) ** 2).sum(-1).mean(0)
        return out

    def dynamic_by_k(self, tau: float) -> Tensor:
        """`(N,)` bool: the Gaussians the decomposition calls dynamic by their stored K alone, K > `tau`,
        and those present for part of the clip, which change over time whatever their motion."""
        return (self.K > tau) | self.lifespan[:, 1].isfinite()

    @torch.no_grad()
    def decompose(
        self,
        tau: float | None = None,
        recompute: bool = True,
        in_place: bool = False,
        keep_static: bool = False,
        also_dynamic: Tensor | None = None,
    ) -> Tensor:
        """Splits into static (`K <= tau`) and dynamic (`K > tau`, or `also_dynamic (N,)`, what
        training's splits read off the optical flow); returns the dynamic mask.

        `keep_static`: a Gaussian already static stays static whatever its K (training's
        re-decompositions on a video ingest, `TrainConfig.redecompose_to_dynamic`): a static Gaussian's K
        is the field's motion where it sits, which was never fitted to it, and turning such
        Gaussians dynamic loses at once what they rendered (docs/method.md, "Decompositions in place").

        `in_place`: each Gaussian whose rendered offsets the decomposition changes (it changes sides,
        or its kNN neighbours do) has its canonical mean, rotation and scale moved by the
        difference of its time-averaged offsets, so that on average over the clip it renders
        where it did. Without it a dynamic Gaussian that turns static jumps by its mean offset:
        K measures how much the offset varies, not how large it is, and on real footage the
        field's mean offsets are larger than their variation (docs/method.md, "Decompositions
        in place")."""
        if tau is not None:
            self.config.tau = tau
        if recompute:
            self.K = self.compute_K()
        dynamic = self.dynamic_by_k(self.config.tau)
        if also_dynamic is not None:
            dynamic = dynamic | also_dynamic
        if keep_static and self.decomposed:
            dynamic &= self.dynamic
        unchanged = self.decomposed and torch.equal(dynamic, self.dynamic)
        before = self.mean_offsets() if in_place and not unchanged else None
        if not unchanged:
            # The graph is carried, as through densification (`set_params`): the Gaussians that
            # stay dynamic keep their neighbours (those who turned static replaced by the row's
            # own Gaussian), and only those that turn dynamic get the nearest ones: a graph
            # rebuilt whole gives fitted Gaussians new neighbours (docs/method.md, "Resume").
            self._knn = self._graph_after_redecompose(dynamic) if self.decomposed else None
        self.dynamic = dynamic
        self.decomposed = True
        if before is not None:
            # (The kNN graph built for `after` is kept, as training keeps it while means move.)
            self.move_canonical(before - self.mean_offsets())
        return self.dynamic

    @torch.no_grad()
    def mean_offsets(self) -> Tensor:
        """`(N, 9)`: each Gaussian's rendered offsets (dx, dr, ds) averaged over
        `K_times` evenly spaced times; zeros for the static ones."""
        n = len(self.params)
        out = torch.zeros(n, 9)
        idx = torch.arange(n) if not self.decomposed else torch.nonzero(self.dynamic).squeeze(1)
        if len(idx):
            T = self.config.K_times
            acc = torch.zeros(len(idx), 9)
            for t in torch.linspace(0, 1, T).tolist():
                acc += self.offsets_at(idx, [t])[0].cat()
            out[idx] = acc / T
        return out

    @torch.no_grad()
    def move_canonical(self, d: Tensor) -> None:
        """Applies offsets `d (N, 9)` = (dx, dr, ds) to the canonical Gaussians as the field
        applies them (`residual_covariance`): means + dx, rotation R(q) exp(dr), scales times
        exp(lambda_s ds). Rows of zeros are left untouched, bit for bit."""
        rows = torch.nonzero(d.abs().sum(-1) > 0).squeeze(1)
        if not len(rows):
            return
        p, d = self.params, d[rows]
        p.means[rows] += d[:, :3]
        p.quats[rows] = quat_multiply(normalize_quats(p.quats[rows]), rotvec_to_quat(d[:, 3:6]))
        scales = self.scales()[rows] * torch.exp(self.config.lambda_s * d[:, 6:9])
        p.log_scales[rows] = torch.log((scales - self.min_scale).clamp_min(1e-8))

    def static_field_dx(self, t: float, count: int) -> Tensor:
        """`(S, 3)` the field's position offsets at `t` for `S <= count` static Gaussians drawn
        at random: L_reg's static term. The static Gaussians render without the field, so
        their rendered offsets are zero and a term over those says nothing; the paper's L_reg
        holds the field's offsets over the static set down. A sample is an unbiased estimate of
        the mean at a fraction of the cost of evaluating the field on every static Gaussian."""
        idx = torch.nonzero(~self.dynamic).squeeze(1)
        if len(idx) > count:
            idx = idx[torch.randint(len(idx), (count,))]
        x = self.params.means.detach()[idx]
        return self.deform.at_times(x, [torch.full((len(x),), float(t))])[0].dx


def otsu_tau(K: Tensor, floor: float, from_share: float = 0.0, bins: int = 128) -> float:
    """A decomposition threshold picked from the distribution of K: Otsu's threshold on log10 K (the
    cut that best separates the still mode from the moving tail), never below `floor` (the
    fixed τ, which says what "still" means for a clean scene). On real footage the field also
    absorbs residual pose error and noise, so almost every Gaussian's K sits above a fixed τ;
    the moving objects are the tail above that mode (docs/method.md, "Settings
    that follow the scene").

    Only the Gaussians whose K is above `from_share` x `floor` take part: those the field leaves
    (almost) still form a third mode, far below the other two on real footage, and splitting
    that off put the cut under the floor, so that nearly every Gaussian deformed."""
    if from_share > 0:
        K = K[K > from_share * floor]
    lk = torch.log10(K.double().clamp_min(1e-12))
    if len(lk) < 2 or float(lk.max() - lk.min()) < 1e-9:
        return floor
    hist = torch.histc(lk, bins=bins, min=float(lk.min()), max=float(lk.max()))
    centers = torch.linspace(float(lk.min()), float(lk.max()), bins + 1, dtype=torch.float64)
    centers = 0.5 * (centers[1:] + centers[:-1])
    w0 = torch.cumsum(hist, 0)
    m0 = torch.cumsum(hist * centers, 0)
    w1, m1 = w0[-1] - w0, m0[-1] - m0
    between = w0 * w1 * (m0 / w0.clamp_min(1e-12) - m1 / w1.clamp_min(1e-12)) ** 2
    k = int(torch.argmax(between[:-1]))
    return max(floor, float(10 ** (0.5 * (centers[k] + centers[k + 1]))))


def decomposition_counts(model: KinematicsGS, static_only: bool = False) -> dict:
    """Gaussian counts; before the first decomposition every Gaussian deforms (all dynamic), and in a
    static run (`--ablate deform`) none does. "spawned": those present for part of the clip
    (train/spawn.py, and their clones)."""
    n = len(model)
    d = 0 if static_only else int(model.dynamic.sum()) if model.decomposed else n
    return {
        "gaussians": n,
        "dynamic": d,
        "static": n - d,
        "dynamic_share": d / max(n, 1),
        "spawned": int(model.lifespan[:, 1].isfinite().sum()),
    }  # present for part of the clip


def K_histogram(K: np.ndarray, bins: int = 64) -> dict:
    """Histogram of log10 K (what the tau slider of the viewers shows)."""
    lv = np.log10(np.clip(K, 1e-12, None))
    counts, edges = np.histogram(lv, bins=bins, range=(-12, 0))
    return {"log10_edges": edges.tolist(), "counts": counts.tolist()}
