"""What training minimises, as methods of `Trainer` (a mixin): the photometric loss of one
frame's render plus the regularisers (L_reg, the K-Planes smoothness, L_ani) and the optical-flow
term."""

from __future__ import annotations

import torch

from ..data.scene import Frame
from ..losses import coarse_l1, gradient_l1, photometric_loss
from ..model.render import camera_tensors, render_model
from ..render.types import Rendered
from .flow import charbonnier, flow_residual


class Objective:
    """`loss_for` and `flow_term`; read the trainer's `model`, `cfg`, `scene`, `views` (frames
    at the step's image size), `noise`, `camera_motion` and pose correction."""

    def loss_for(self, frame: Frame, it: int) -> tuple[torch.Tensor, Rendered]:
        c, scene, model = self.cfg, self.scene, self.model
        # (on the schedules' clock: a time budget may lengthen or shorten the run, `watch_tail`)
        noise = 0.0 if self.static_only else self.noise.sigma(self.schedule_iteration(it)[0])
        t = frame.time
        if noise > 0 and not c.noise_per_gaussian:  # one shift for every Gaussian
            t, noise = t + noise * float(torch.randn(())), 0.0
        camera_motion = None if self.camera_motion is None else self.camera_motion.get(frame.id)
        k = self.image_divisor(it)
        exposure = self.exposure if self.fitted_exposure is None else self.fitted_exposure.value()
        out, g = render_model(
            model,
            self.views.camera(frame, k),
            t,
            exposure,
            scene.dt,
            self.background,
            noise=noise,
            static=self.static_only,
            camera_motion=camera_motion,
            velocity=False,
            world_transform=self.world_transform(frame),
            absgrad=self.strategy.wants_absgrad(it),
        )
        gt = self.views.image(frame, k)
        loss = photometric_loss(out.image, gt, c.lambda_dssim)
        if c.lambda_coarse > 0:
            loss = loss + c.lambda_coarse * coarse_l1(out.image, gt, c.coarse_factor)
        if c.lambda_grad > 0:
            loss = loss + c.lambda_grad * gradient_l1(out.image, gt)
        if c.lambda_flow > 0 and frame.id in self.flows and g.dynamic.any():
            loss = loss + c.lambda_flow * self.flow_term(frame, out, g, k)
        if not self.static_only:
            if c.lambda_reg > 0 and g.offsets_dx is not None:
                # L_reg: mean |dx| over the dynamic set plus mean |dx| over the static set. The
                # static Gaussians render without the field (their rendered dx is 0), so their
                # term is the field's offsets under a sample of them, when reg_static_samples > 0.
                norms = g.offsets_dx.norm(dim=-1)
                dyn = g.dynamic
                reg = norms[dyn].mean() if dyn.any() else norms.sum() * 0
                if model.decomposed and c.reg_static_samples > 0 and (~dyn).any():
                    reg = reg + model.static_field_dx(t, c.reg_static_samples).norm(dim=-1).mean()
                loss = loss + c.lambda_reg * reg
            if c.lambda_tv > 0:
                loss = loss + c.lambda_tv * model.deform.planes.smoothness()
        if c.lambda_ani > 0:
            s = model.scales()
            loss = loss + c.lambda_ani * (s.max(-1).values / (s.min(-1).values + c.eps_ani)).mean()
        return loss, out

    def flow_term(self, frame: Frame, out: Rendered, g, k: int = 1) -> torch.Tensor:
        """The flow term (train/flow.py) for the Gaussians that deform: their positions at this
        frame's time as rendered, and at the next frame's time, each under its own frame's
        pose correction when poses are refined; at image divisor `k` (the render's size), with
        the residuals in full-size pixels so that the term weighs the same at every size. The
        next position is the rendered one moved over the frame interval by a velocity the step
        already has; the field is not evaluated again (a second evaluation cost 15-39 % of a
        step):

        - where K.R. computed the dynamic Gaussians' velocity (after the decomposition, exposure > 0),
          that velocity: the term supervises what K.R.'s blur reads, and it does not see the
          time noise (the rendered position is at a jittered time; the velocity hardly changes
          over one);
        - elsewhere (before the decomposition, after K.R.'s mid-run check turned it off, the D3DGS-like
          baseline throughout), a Gaussian on its own line (`spawned_motion="own"`) moves by its
          `own_velocity`, and every other one is read as standing still, so that the flow
          asks for the depth whose parallax explains it. Reading the field at the next time
          instead measured no better and slower (docs/real-footage.md, "An optical-flow term")."""
        j, flow = self.views.flow(frame, k)
        nxt = self.scene.train_frames[j]
        model = self.model
        live = g.extras.get("dynamic_velocity")
        if live is not None:
            idx, v = live
        else:
            idx = torch.nonzero(g.dynamic).squeeze(1)
            v = torch.zeros(len(idx), 3)
            if model.config.spawned_motion == "own":
                own = model.lifespan[idx, 1].isfinite()
                v = torch.where(own[:, None], model.own_velocity.index_select(0, idx), v)
        # (index_select, not [idx]: its backward is the faster one, model/dynamic.py)
        x_next = model.params.means.index_select(0, idx) + g.offsets_dx.index_select(0, idx) + v * (nxt.time - frame.time)
        # (g.means carry this frame's pose correction; the next positions get the next frame's.)
        cameras = camera_tensors(self.views.camera(frame, k)), camera_tensors(self.views.camera(nxt, k))
        res = flow_residual(g.means.index_select(0, idx), self.posed(x_next, nxt), *cameras, flow, out.depth)
        return charbonnier(res * k)
