"""Adaptive density control (3DGS): clone small and split large Gaussians with large
screen-space gradients, prune transparent ones, reset opacities. A small strategy class in the
spirit of gsplat's: `accumulate` after each backward, `step` once per iteration."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..model.dynamic import KinematicsGS
from ..model.gaussians import GaussianParams, set_param
from ..render.covariance import quat_to_rotmat
from ..render.types import Rendered


@dataclass
class DensifyStrategy:
    """Its fields are the configuration (`TrainConfig.densify`, set with `--set densify.KEY=VALUE`);
    the running gradient statistics are per-Gaussian state (`state`: grad_sum and count, (N,)
    each), created fresh for each copy (`dataclasses.replace` gives the trainer its own), resized
    with the Gaussians by whoever prunes or adds them (`KinematicsGS.keep_gaussians` /
    `add_gaussians` take it), and kept in checkpoints by the trainer."""

    # Clone (small) or split (large) a Gaussian whose mean screen-space gradient, in NDC units as
    # in the 3DGS literature, reaches this.
    grad_threshold: float = 1e-4
    start: int = 500  # the first iteration that densifies
    stop: int = 10_000  # densify before this iteration
    every: int = 100
    prune_opacity: float = 0.005  # prune Gaussians less opaque than this at their most opaque time
    percent_dense: float = 0.01  # "small" (cloned, not split): largest scale below this share of the extent
    opacity_reset_at: tuple = (3000,)  # iterations at which every rendered opacity is capped at 0.01
    max_gaussians: int = 60_000  # the budget: beyond it only the largest gradients densify
    # AbsGS's statistic: the norm of the per-pixel absolute screen gradients summed, instead of
    # the norm of their sum. A large Gaussian over detail (a blurred-out moving person) gets
    # pixel gradients that cancel in the sum and so is never split; their absolute values do
    # not cancel. Its values run larger: AbsGS pairs it with a threshold about 4x the usual.
    absgrad: bool = False
    extent: float = 1.0  # the scene's extent, normalised scene units

    def __post_init__(self):
        self.opacity_reset_at = tuple(self.opacity_reset_at)
        self.state: dict[str, torch.Tensor] = {}
        self.reset(0)

    def reset(self, n: int) -> None:
        """Zero statistics for `n` Gaussians."""
        self.state.update(grad_sum=torch.zeros(n), count=torch.zeros(n))

    def _ensure(self, n: int) -> None:
        have = len(self.state["grad_sum"])
        if have == 0:
            self.reset(n)
        elif have != n:  # someone resized the Gaussians without passing `state` along
            raise RuntimeError(f"densification statistics cover {have} Gaussians, the model has {n}")

    def wants_absgrad(self, it: int) -> bool:
        """Whether step `it`'s render must leave the absolute gradients `accumulate` reads."""
        return self.absgrad and it < self.stop

    def accumulate(self, out: Rendered, width: int, height: int) -> None:
        g = out.screen_grad(self.absgrad)
        if g is None:
            return
        self._ensure(len(g))
        # Pixel gradients -> NDC units, so thresholds match the 3DGS literature.
        g = g * g.new_tensor([width / 2.0, height / 2.0])
        vis = out.radii > 0
        self.state["grad_sum"][vis] += g[vis].norm(dim=-1)
        self.state["count"][vis] += 1

    def step(self, model: KinematicsGS, optimizer, it: int) -> bool:
        """Densifies and prunes when `it` is a densification count. Returns True when the set
        of Gaussians changed. (The opacity reset is `reset_opacities`, which the trainer runs
        after every other event of the count.)"""
        if self.start <= it < self.stop and it % self.every == 0 and it > 0:
            self._densify_and_prune(model, optimizer)
            return True
        return False

    def reset_opacities(self, model: KinematicsGS, optimizer, it: int) -> None:
        """Caps every Gaussian's opacity at 0.01 as rendered at its most opaque time, when `it`
        is an opacity-reset count: each logit at most logit(0.01) less what it gains at its
        most opaque time (`KinematicsGS.peak_opacity_offsets`). Capping the logit alone
        would leave a dynamic Gaussian that the time opacity fades at every time below the
        rasteriser's 1/255, where it gets no gradient and never comes back, and a moving
        person became a ghost of static Gaussians (docs/real-footage.md, "The opacity reset")."""
        if it in self.opacity_reset_at:
            op = model.params.opacity_logits.detach()
            cap = torch.logit(torch.tensor(0.01)) - model.peak_opacity_offsets()
            model.params = set_param(model.params, optimizer, "opacity_logits", torch.minimum(op, cap))

    @torch.no_grad()
    def _densify_and_prune(self, model: KinematicsGS, optimizer) -> None:
        n = len(model)
        self._ensure(n)
        avg = self.state["grad_sum"] / self.state["count"].clamp_min(1)
        big = avg >= self.grad_threshold
        scales = model.scales().detach()
        small = scales.max(-1).values <= self.percent_dense * self.extent
        room = max(self.max_gaussians - n, 0)
        clone = big & small
        split = big & ~small
        # Respect the budget: keep the largest gradients.
        want = int(clone.sum() + split.sum())
        if want > room:
            order = torch.argsort(torch.where(big, avg, torch.zeros_like(avg)), descending=True)
            allowed = torch.zeros(n, dtype=torch.bool)
            allowed[order[:room]] = True
            clone &= allowed
            split &= allowed
        p = model.params
        heirs = torch.full((n,), -1, dtype=torch.long)
        new_parts: list[GaussianParams] = []
        parents = []
        if clone.any():
            new_parts.append(GaussianParams(*(v.detach()[clone] for _, v in p.items())))
            parents.append(torch.nonzero(clone).squeeze(1))
        if split.any():
            idx = torch.nonzero(split).squeeze(1)
            # The first child takes its parent's place in its neighbours' kNN rows.
            heirs[idx] = n + int(clone.sum()) + torch.arange(len(idx))
            R = quat_to_rotmat(p.quats.detach()[idx])
            s = scales[idx]
            for _ in range(2):
                offset = (R @ (torch.randn_like(s) * s)[..., None]).squeeze(-1)
                child = GaussianParams(*(v.detach()[idx].clone() for _, v in p.items()))
                child.means = child.means + offset
                child.log_scales = torch.log((s / 1.6 - model.min_scale).clamp_min(1e-8))
                new_parts.append(child)
                parents.append(idx)
        for part, par in zip(new_parts, parents):
            model.add_gaussians(part, par, optimizer, self.state)
        params = model.params
        # Prune: split parents, transparent and huge Gaussians. Transparent as rendered at its
        # most opaque time: one the time opacity fades below the threshold at every time adds
        # nothing to any frame and, under the rasteriser's 1/255, gets no gradient either, so
        # it would stay to the end, pure cost (docs/real-footage.md, "The opacity reset").
        keep = torch.ones(len(params), dtype=torch.bool)
        keep[:n][split] = False
        opac = torch.sigmoid(params.opacity_logits.detach() + model.peak_opacity_offsets())
        keep &= opac >= self.prune_opacity
        big_world = (torch.exp(params.log_scales.detach()).max(-1).values + model.min_scale) > 0.5 * self.extent
        keep &= ~big_world
        if keep.sum() < 4:  # never prune everything
            keep[:] = True
        heirs = torch.cat([heirs, heirs.new_full((len(params) - n,), -1)])
        model.keep_gaussians(keep, optimizer, self.state, heirs)
        self.reset(len(model))  # 3DGS: the statistics start again after each densification
