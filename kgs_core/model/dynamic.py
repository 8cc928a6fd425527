"""The Kinematics-GS model: canonical Gaussians + deformation field + static/dynamic decomposition +
coarse-to-fine offsets + kinematic covariance, evaluated at any time `t`.

`KinematicsGS.at(t, ...)` returns the Gaussians to rasterize; it is what training, the server,
the viewers and the exporters all call. The training path gathers the dynamic rows with
`index_select` and writes them back with `index_copy`, never `x[idx]` / `index_put`, whose
backward is serial on CPU (docs/results.md, "Training speed").
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch
from torch import Tensor, nn

from ..render import packed_covariance
from ..render.covariance import pack_covariance, quat_to_rotmat, unpack_covariance
from .config import ModelConfig
from .decomposition import Decomposition
from .deformation import DeformationField, FineResidual, Offsets, TimeOpacity
from .gaussians import GaussianParams, GaussiansAt, append, presence, select
from .kinematics import motion_blur_covariance, refine_covariance, residual_covariance, safe_norm, so3_exp, velocity_from_offsets
from .neighbours import NeighbourGraph, checked_knn
from .per_gaussian import PerGaussian, check_rows


class Deformed(NamedTuple):
    """Dynamic Gaussians at one time (`KinematicsGS._deform`)."""

    means: Tensor  # (D, 3)
    covars6: Tensor  # (D, 6) packed
    velocity: Tensor | None  # (D, 3); None where the caller said it will not read it
    dx: Tensor  # (D, 3) position offsets (L_reg)
    sweep: Tensor | None  # (D, 3) the convolve form's displacement over the exposure; None: no blur


class KinematicsGS(NeighbourGraph, Decomposition, nn.Module):
    """Canonical Gaussians, the deformation field and the decomposition, evaluated at any time (`at`).
    C.F.'s neighbour graph is `NeighbourGraph`'s (model/neighbours.py), the decomposition by K
    `Decomposition`'s (model/decomposition.py)."""

    def __init__(self, params: GaussianParams, config: ModelConfig):
        super().__init__()
        self.config = config
        self.params = params
        c = config
        self.deform = DeformationField(
            c.deform_spatial, c.deform_temporal, c.deform_features, c.deform_multires, c.deform_width, c.deform_depth, c.bound
        )
        self.fine = FineResidual(c.feature_dim)
        self.time_opacity = TimeOpacity(c.feature_dim) if c.time_opacity else None
        self.kappa = nn.Parameter(torch.tensor(float(c.kappa_init)))
        n = len(params)
        self.decomposed = False  # before the decomposition every Gaussian deforms
        # Flags, K, lifespans and own velocities, one row per Gaussian (model/per_gaussian.py).
        self.per_gaussian = PerGaussian.empty(n)
        self.min_scale = 0.0  # FLoD level-dependent lower bound of the scales
        self._knn: Tensor | None = None
        self._knn_mean: tuple | None = None  # (knn and dropped rows it was built from, W, W^T): neighbour_mean

    # ------------------------------------------------------------ bookkeeping

    def __len__(self) -> int:
        return len(self.params)

    def network_parameters(self) -> dict[str, list[Tensor]]:
        return {
            "grid": list(self.deform.planes.parameters()),
            "deform_mlp": list(self.deform.mlp.parameters()),
            "fine_mlp": list(self.fine.parameters()) + ([] if self.time_opacity is None else list(self.time_opacity.parameters())),
            "kappa": [self.kappa],
        }

    # The per-Gaussian state (model/per_gaussian.py), read and written by name (the decomposition
    # sets `dynamic`, spawning `lifespan`), is resized in lock-step with the parameters, their
    # Adam moments and a strategy's statistics only through `set_params`, `keep_gaussians` and
    # `add_gaussians`, C.F.'s graph included: carried, not rebuilt, since each fine residual is
    # fitted to its neighbours' offsets (docs/real-footage.md, "The paper preset on walk"). Setting
    # a field makes a new container, so that a shallow copy of the model (the server's τ copies)
    # never writes into the container it shares with the original.
    dynamic = property(lambda self: self.per_gaussian.dynamic, lambda self, v: self._set_state(dynamic=v))
    K = property(lambda self: self.per_gaussian.K, lambda self, v: self._set_state(K=v))
    lifespan = property(lambda self: self.per_gaussian.lifespan, lambda self, v: self._set_state(lifespan=v))
    own_velocity = property(lambda self: self.per_gaussian.own_velocity, lambda self, v: self._set_state(own_velocity=v))

    def _set_state(self, **field: Tensor) -> None:
        self.per_gaussian = dataclasses.replace(self.per_gaussian, **field)

    def set_params(self, params: GaussianParams, per_gaussian: PerGaussian, knn: Tensor | None = None) -> None:
        """`knn`: the graph over the new dynamic set; None: rebuilt when next needed."""
        if any(len(v) != len(params) for _, v in per_gaussian.items()):
            raise ValueError(
                f"per-Gaussian state out of step: {len(params)} Gaussians, "
                + ", ".join(f"{len(v)} rows of {k}" for k, v in per_gaussian.items())
            )
        if knn is not None and len(knn) != int(per_gaussian.dynamic.sum()):
            raise ValueError(f"kNN graph out of step: {len(knn)} rows for {int(per_gaussian.dynamic.sum())} dynamic Gaussians")
        self.params = params
        self.per_gaussian = per_gaussian
        self._knn = knn

    def keep_gaussians(
        self, keep: Tensor, optimizer: torch.optim.Adam | None = None, state: dict[str, Tensor] | None = None, heirs: Tensor | None = None
    ) -> None:
        """Keeps the Gaussians where `keep (N,) bool` is true (pruning): parameters, Adam
        moments, the per-Gaussian state, the kNN graph, and the (N, ...) tensors of `state` (a
        strategy's statistics, replaced in the dict).

        In the graph a removed neighbour is replaced by its heir, `heirs (N,)` (a densification split parent's
        child; -1: none), or else by the row's own Gaussian (as `knn_radius` does)."""
        self.set_params(select(self.params, optimizer, keep), self.per_gaussian.select(keep), self._graph_after_keep(keep, heirs))
        for k, v in (state or {}).items():
            state[k] = v[keep]

    def add_gaussians(
        self,
        new: GaussianParams,
        parents: Tensor,
        optimizer: torch.optim.Adam | None = None,
        state: dict[str, Tensor] | None = None,
        lifespan: Tensor | None = None,
        own_velocity: Tensor | None = None,
    ) -> None:
        """Appends Gaussians (densification: clones and split children); each inherits its
        parent's per-Gaussian state (dynamic flag, K, lifespan, own velocity; or takes `lifespan
        (M, 2)`, `own_velocity (M, 3)` when given) and kNN neighbours, `parents (M,)` indices
        into the current set, and starts with zero Adam moments and zeros in `state`."""
        knn = self._graph_after_add(parents)
        self.set_params(
            append(self.params, optimizer, new), self.per_gaussian.append(parents, lifespan=lifespan, own_velocity=own_velocity), knn
        )
        for k, v in (state or {}).items():
            state[k] = torch.cat([v, v.new_zeros((len(parents), *v.shape[1:]))])

    def scales(self) -> Tensor:
        # Clamped so that exp cannot overflow float32 (e^88) or underflow to 0 at extreme logits.
        return torch.exp(self.params.log_scales.clamp(-30.0, 30.0)) + self.min_scale

    # ------------------------------------------------------------ evaluation at time t

    def offsets(self, idx: Tensor, t: float, noise: float = 0.0) -> Offsets:
        """Offsets of the Gaussians `idx` (all of them, or the dynamic set) at time `t`."""
        return self.offsets_at(idx, [t], noise)[0]

    def offsets_at(self, idx: Tensor, times: list[float], noise: float = 0.0, shared_fine: bool = False) -> list[Offsets]:
        """Offsets of the Gaussians `idx` at each of `times`, in one batched evaluation of the
        field (and of the fine residual). `noise` (training's time jitter) moves the first
        time only: the others are the physical velocity's samples around it.

        `shared_fine`: the fine residual is evaluated at the first time only and added at every
        time, so that differences between the times are the coarse motion's. The physical
        velocity uses this (docs/method.md, "Velocity"): the per-Gaussian residual made the
        velocities noisier (error 0.26 against 0.07 px/frame on the sheet), and evaluating it
        at three times cost a sixth of a training step."""
        n = len(idx)
        tt = [torch.full((n,), float(t)) for t in times]
        if noise > 0:
            tt[0] = tt[0] + noise * torch.randn(n)
        # The field is evaluated for the rows that read it: under "own" not for the spawned
        # Gaussians (on real footage most of the dynamic set by the end), whose rows stay zero
        # here and are replaced by their own line in `_spawned_offsets`.
        own = self.lifespan[idx, 1].isfinite() if self.config.spawned_motion == "own" else None
        rows = None if own is None or not own.any() else torch.nonzero(~own).squeeze(1)
        field_idx, field_tt = (idx, tt) if rows is None else (idx[rows], [t[rows] for t in tt])
        raws = [_scatter_rows(r.cat(), rows, n) for r in self.deform.at_times(self.params.means.index_select(0, field_idx), field_tt)]
        if not (self.decomposed and self.config.coarse_to_fine):
            return self._spawned_offsets(idx, tt, [Offsets.from_cat(r) for r in raws])
        # One sparse product for all times: (D, 9 M) offsets side by side.
        coarse = self.neighbour_mean(torch.cat(raws, 1)).split(9, 1)
        features = self.params.features.index_select(0, field_idx)
        if shared_fine:
            fine = _scatter_rows(self.fine(features, field_tt[0]).cat(), rows, n)
            return self._spawned_offsets(idx, tt, [Offsets.from_cat(c + fine) for c in coarse])
        fine = self.fine(features.repeat(len(times), 1), torch.cat(field_tt)).cat().split(len(field_idx))
        fine = [_scatter_rows(f, rows, n) for f in fine]
        return self._spawned_offsets(idx, tt, [Offsets.from_cat(c + f) for c, f in zip(coarse, fine)])

    def _spawned_offsets(self, idx: Tensor, times: list[Tensor], offsets: list[Offsets]) -> list[Offsets]:
        """The field's `offsets` of the Gaussians `idx` at `times` ((D,) each), with the rows of
        Gaussians present for part of the clip (bounded `lifespan`: spawned ones,
        train/spawn.py) replaced as `spawned_motion` says. Either way their loss does not train
        the field: a Gaussian made to fill one frame pulls the field cells it shares with the
        background towards that frame's motion, bending the background at every time
        (docs/real-footage.md, "Spawned Gaussians").

        "own": the straight line `own_velocity (t - centre)`, no rotation or scale change, so
        that it stays on the pixels it was made for at its frame whatever the field learns
        later, and moves as the flow there said to the frames around it (`offsets_at` does not
        evaluate the field for it, and C.F. leaves it out of others' neighbourhoods). "field": the field's
        offsets, detached (it follows its parent's neighbourhood of the field)."""
        bounded = self.lifespan[idx, 1].isfinite()
        if not bounded.any():
            return offsets
        rows = bounded[:, None]
        if self.config.spawned_motion == "field":
            return [Offsets.from_cat(torch.where(rows, o.cat().detach(), o.cat())) for o in offsets]
        centre, velocity = self.lifespan[idx, 0], self.own_velocity.index_select(0, idx)
        still = torch.zeros(len(idx), 6)
        return [
            Offsets.from_cat(torch.where(rows, torch.cat([velocity * (t - centre)[:, None], still], 1), o.cat()))
            for o, t in zip(offsets, times)
        ]

    def positions(self, idx: Tensor, t: float, noise: float = 0.0) -> tuple[Tensor, Offsets]:
        off = self.offsets(idx, t, noise)
        return self.params.means.index_select(0, idx) + off.dx, off

    def at(
        self,
        t: float,
        exposure: float | Tensor = 0.0,
        dt: float = 1.0,
        noise: float = 0.0,
        camera_motion: tuple[Tensor, Tensor] | None = None,
        velocity: bool = True,
    ) -> GaussiansAt:
        """Gaussians at time `t`. `exposure` (fraction of the frame interval `dt`) sets the
        kinematic elongation: 0 renders sharp. `noise` is the training-time jitter of `t`.
        `camera_motion = (A (3, 3), b (3,))`: the camera's own motion during the exposure, as
        the world-frame velocity `A x + b` it gives a still point `x` relative to the camera
        (`camera_motion_from_poses`); every Gaussian is then blurred along its velocity relative
        to the camera (`convolve` form only). `velocity=False`: the caller will not read
        `.velocity`, which is then None where computing it can be skipped (`_deform`)."""
        p = self.params
        n = len(p)
        scales = self.scales()
        cov6 = packed_covariance(p.quats, scales)  # C++ when built: the static path is most of N
        means = p.means
        velocities = torch.zeros(n, 3)
        dx_all = torch.zeros(n, 3)
        idx = torch.arange(n) if not self.decomposed else torch.nonzero(self.dynamic).squeeze(1)
        # (Before the decomposition every Gaussian deforms without K.R., so nothing is blurred then.)
        blur_camera = camera_motion is not None and exposure > 0 and self.config.kr_form == "convolve" and self.decomposed
        cov6_canonical, sweep_all = cov6, None
        if blur_camera:
            # Every Gaussian blurred by the camera's motion (the dynamic rows are replaced below):
            # dense, since most of N is static and gathering the static rows cost milliseconds.
            A, b = camera_motion
            sweep_all = (means.detach() @ A.T + b) * (dt * exposure)
            cov6 = motion_blur_covariance(cov6, sweep_all)
        sweep = None if sweep_all is None else (None, sweep_all)
        extras = {}
        if len(idx):
            d = self._deform(
                idx,
                t,
                exposure,
                dt,
                noise,
                scales.index_select(0, idx),
                cov6_canonical.index_select(0, idx),
                camera_motion if blur_camera else None,
                velocity,
            )
            means = means.index_copy(0, idx, d.means)
            cov6 = cov6.index_copy(0, idx, d.covars6)
            velocities = None if d.velocity is None else velocities.index_copy(0, idx, d.velocity.detach())
            # Differentiable, for the flow term (train/flow.py), and only where K.R. computed it:
            # without K.R. the zeros are no measurement (`Trainer.flow_term` reads the motion
            # the step has instead).
            if d.velocity is not None and self.config.kinematic and self.decomposed:
                extras["dynamic_velocity"] = (idx, d.velocity)
            dx_all = dx_all.index_copy(0, idx, d.dx)
            if sweep_all is not None:  # (without K.R. the dynamic Gaussians are not blurred)
                rows = d.sweep if d.sweep is not None else torch.zeros_like(d.means)
                sweep = (None, sweep_all.index_copy(0, idx, rows))
            elif d.sweep is not None:
                sweep = (idx, d.sweep)
        opacities = self.present(p.opacities, t)
        if self.time_opacity is not None and self.decomposed and len(idx):
            opacities = opacities.index_copy(0, idx, opacities.index_select(0, idx) * self.opacity_factor(idx, t))
        return GaussiansAt(
            means=means,
            covars6=cov6,
            opacities=opacities,
            sh=p.sh(),
            dynamic=self.dynamic if self.decomposed else torch.ones(n, dtype=torch.bool),
            velocity=velocities,
            offsets_dx=dx_all,
            sweep=sweep,
            extras=extras,
        )

    def at_dynamic(
        self, t: float, exposure: float = 0.0, dt: float = 1.0, velocity: bool = True, camera_motion: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, GaussiansAt]:
        """Only the dynamic Gaussians at time `t` (what changes when a viewer scrubs time):
        `(idx (D,), GaussiansAt of D)`; the static ones are `at_static()` restricted to the rest.
        `velocity` and `camera_motion` as in `at`."""
        p = self.params
        idx = torch.arange(len(p)) if not self.decomposed else torch.nonzero(self.dynamic).squeeze(1)
        scales = self.scales()[idx]
        cov6 = packed_covariance(p.quats[idx], scales)
        if len(idx):
            d = self._deform(idx, t, exposure, dt, 0.0, scales, cov6, camera_motion if exposure > 0 else None, velocity=velocity)
        else:
            d = Deformed(p.means[idx], cov6, torch.zeros(0, 3), torch.zeros(0, 3), None)
        opacities = self.present(p.opacities, t)[idx] * self.opacity_factor(idx, t)
        return idx, GaussiansAt(
            means=d.means,
            covars6=d.covars6,
            opacities=opacities,
            sh=p.sh()[idx],
            dynamic=torch.ones(len(idx), dtype=torch.bool),
            velocity=None if d.velocity is None else d.velocity.detach(),
            offsets_dx=d.dx,
            sweep=None if d.sweep is None else (None, d.sweep),
        )

    def _time_faded(self, idx: Tensor) -> Tensor:
        """Positions in `idx` (dynamic Gaussians) of those the time opacity acts on: the ones the
        field moves after the decomposition, not the spawned ones on their own line (their `lifespan`
        does that job); none without a time opacity or before the decomposition."""
        if self.time_opacity is None or not self.decomposed or not len(idx):
            return idx.new_zeros(0)
        return torch.nonzero(~self.lifespan[idx, 1].isfinite()).squeeze(1)

    @torch.no_grad()
    def peak_opacity_offsets(self, times: int = 33) -> Tensor:
        """`(N,)` what each Gaussian's opacity logit gains at its most opaque time: for those
        the time opacity fades (`_time_faded`), the largest offset over `times` evenly spaced
        times of the clip; 0 for the rest (a spawned Gaussian's `lifespan` peaks at 1). 33
        times find the peak to within 0.1 in logit on trained real-clip models (against 257)."""
        peak = torch.zeros(len(self.params))
        idx = torch.nonzero(self.dynamic).squeeze(1)
        rows = idx[self._time_faded(idx)]
        if len(rows):
            features = self.params.features[rows]
            offsets = torch.stack([self.time_opacity(features, torch.full((len(rows),), float(t))) for t in torch.linspace(0, 1, times)])
            peak[rows] = offsets.max(0).values
        return peak

    def opacity_factor(self, idx: Tensor, t: float) -> Tensor:
        """`(len(idx),)` factor on the opacities of the Gaussians `idx` (the dynamic set) at
        `t` from `TimeOpacity` (`config.time_opacity`): sigmoid(logit + o(t)) / sigmoid(logit)
        for those it acts on (`_time_faded`), 1 for the rest and everywhere without it."""
        ones = torch.ones(len(idx))
        rows = self._time_faded(idx)
        if not len(rows):
            return ones
        faded = idx[rows]
        logit = self.params.opacity_logits.index_select(0, faded)
        offset = self.time_opacity(self.params.features.index_select(0, faded), torch.full((len(rows),), float(t)))
        # sigmoid(l + o) / sigmoid(l), in logs: no 0 / 0 for a nearly transparent Gaussian.
        F = torch.nn.functional
        return ones.index_copy(0, rows, torch.exp(F.logsigmoid(logit + offset) - F.logsigmoid(logit)))

    def present(self, opacities: Tensor, t: float) -> Tensor:
        """`opacities (N,)` scaled by each Gaussian's presence at `t` (`lifespan`); unchanged
        when every Gaussian is present at every time."""
        if not self.lifespan[:, 1].isfinite().any():
            return opacities
        return opacities * presence(self.lifespan, t)

    def _deform(
        self,
        idx: Tensor,
        t: float,
        exposure: float | Tensor,
        dt: float,
        noise: float,
        scales: Tensor,
        cov6_pred: Tensor,
        camera_motion: tuple[Tensor, Tensor] | None = None,
        velocity: bool = True,
    ) -> "Deformed":
        """The Gaussians `idx` deformed to time `t` (`Deformed`); `cov6_pred` is their packed
        canonical covariance. `velocity=False` (the caller will not read it): under the
        convolve form at exposure 0 the covariance
        gets `(0^2 / 12) v v^T`, so the velocity's two extra field samples are skipped, the
        covariance is the residual one (the same matrix) and the velocity is None.

        Every combination of the flags, in one place (`e` the exposure; the position is always
        the canonical mean plus the field's offset, coarse kNN mean + fine residual under C.F.,
        `coarse_to_fine`, the field's own offset without it):

        - Before the decomposition, or `kinematic=False` (`--ablate kr`, `decompose`): velocity zeros (None
          with `velocity=False`); covariance residual, `R(q) exp(dr)` and `s exp(lambda_s ds)`; no blur sweep.
        - K.R., `kr_form="convolve"` (the default): velocity `"physical"`, the central
          difference over `t +- h` with `h = dt max(e, 1/2) / 2` and C.F.'s fine residual shared
          (the coarse motion's), or `"paper"`, `dx / dt`; covariance residual
          `+ (dt e)^2 / 12 v_rel v_rel^T`, `v_rel` being `v` plus the camera's own motion when
          `camera_motion` is given; sweep `v_rel dt e` when `e > 0`.
        - K.R., `kr_form="paper"`: velocity as above; covariance by eqs. 9-14 in the `basis`
          frame (`refine_covariance`: `basis` matters only here) from `kr_inputs`' Σ and r_z;
          `camera_motion` ignored; no sweep.
        - K.R., convolve, `e = 0`, `velocity=False`: velocity None (not computed); covariance
          residual (what the convolve form gives at `e = 0`); no sweep.

        `velocity_grad=False` takes the two extra samples without gradients (same values). Static
        Gaussians never reach here: `at` gives them their canonical covariance, blurred along
        the camera's motion alone under `camera_motion` (convolve form, `e > 0`, after the decomposition)."""
        p, cfg = self.params, self.config
        skip_velocity = not velocity and exposure == 0 and cfg.kr_form == "convolve"
        kinematic = cfg.kinematic and self.decomposed and not skip_velocity
        # The physical velocity's two samples around t share one batched field evaluation with t.
        # (`exposure` may be a learned 0-d tensor, train/exposure.py: the step needs no gradient.)
        h = 0.5 * dt * max(float(exposure.detach() if isinstance(exposure, Tensor) else exposure), 0.5)
        physical = kinematic and cfg.velocity == "physical"
        if physical and not cfg.velocity_grad:
            off = self.offsets_at(idx, [t], noise)[0]
            with torch.no_grad():
                offs = [off, *self.offsets_at(idx, [t + h, t - h], shared_fine=True)]
        else:
            offs = self.offsets_at(idx, [t, t + h, t - h] if physical else [t], noise, shared_fine=True)
            off = offs[0]
        x_t = p.means.index_select(0, idx) + off.dx
        quats = p.quats.index_select(0, idx)
        if kinematic:
            v = velocity_from_offsets(offs, h, dt)
        sweep = None
        if kinematic and cfg.kr_form == "convolve":
            v_rel = v if camera_motion is None else v + x_t.detach() @ camera_motion[0].T + camera_motion[1]
            sweep = v_rel * (dt * exposure)
            cov6 = motion_blur_covariance(residual_covariance(quats, scales, off, cfg.lambda_s), sweep)
            if not exposure > 0:
                sweep = None
        elif kinematic:
            speed = safe_norm(v)
            if cfg.kr_inputs == "predicted":  # the field's prediction: R(q) exp(dr), s exp(lambda_s ds)
                R, axis_scales = quat_to_rotmat(quats) @ so3_exp(off.dr), scales * torch.exp(cfg.lambda_s * off.ds)
                cov6_pred = residual_covariance(quats, scales, off, cfg.lambda_s)
            else:
                R, axis_scales = quat_to_rotmat(quats).detach(), scales.detach()
            r_z = torch.gather(R, 2, axis_scales.argmax(-1)[:, None, None].expand(-1, 3, 1)).squeeze(-1)
            cov6 = pack_covariance(
                refine_covariance(
                    unpack_covariance(cov6_pred),
                    v,
                    speed * dt * exposure,
                    off.ds,
                    off.dr,
                    r_z,
                    self.kappa,
                    speed * dt,
                    basis=cfg.basis,
                    lambda_s=cfg.lambda_s,
                    still_len=cfg.still_len,
                )
            )
        else:
            # Without K.R. (and during warm-up): D3DGS-style residual rotation and scale.
            v = None if not velocity else torch.zeros_like(x_t)
            cov6 = residual_covariance(quats, scales, off, cfg.lambda_s)
        return Deformed(x_t, cov6, v, off.dx, sweep)

    def at_static(self) -> GaussiansAt:
        """The canonical Gaussians, no deformation (the static 3DGS baseline)."""
        p = self.params
        return GaussiansAt(
            means=p.means,
            covars6=packed_covariance(p.quats, self.scales()),
            opacities=p.opacities,
            sh=p.sh(),
            dynamic=torch.zeros(len(p), dtype=torch.bool),
        )

    # ------------------------------------------------------------ persistence

    def state(self) -> dict:
        return {
            "config": self.config.to_dict(),
            "params": {k: v.detach().clone() for k, v in self.params.items()},
            "networks": {k: v for k, v in self.state_dict().items()},
            "decomposed": self.decomposed,
            **self.per_gaussian.state(),
            "min_scale": self.min_scale,
            # The kNN graph is rebuilt only when the dynamic set changes, from the positions of
            # that moment; a resumed run must reuse it, not rebuild it from later positions.
            "knn": None if self._knn is None else self._knn.clone(),
        }

    @classmethod
    def from_state(cls, state: dict) -> "KinematicsGS":
        params = GaussianParams(**{k: v.clone().requires_grad_(True) for k, v in state["params"].items()})
        n = len(params)
        check_rows(params.items(), n, "params.")
        model = cls(params, ModelConfig.from_dict(state["config"]))
        model.load_state_dict(state["networks"])
        model.decomposed = bool(state["decomposed"])
        model.per_gaussian = PerGaussian.from_state(state, n)
        model.min_scale = float(state["min_scale"])
        model._knn = checked_knn(state.get("knn"), int(model.dynamic.sum()))  # absent in older runs
        return model


def _scatter_rows(x: Tensor, rows: Tensor | None, n: int) -> Tensor:
    """`x (M, C)` placed at `rows (M,)` of an `(n, C)` tensor of zeros (`x` itself when `rows`
    is None: every row)."""
    return x if rows is None else x.new_zeros(n, x.shape[1]).index_copy(0, rows, x)
