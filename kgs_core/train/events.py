"""The training schedule's events, as methods of `Trainer` (a mixin): the static/dynamic decompositions
and their reading of the optical flow, spawning where the render misses something that moves,
K.R.'s mid-run check, and the end of a FLoD level (importance prune, snapshot, next level)."""

from __future__ import annotations

import statistics
import time

import numpy as np
import torch
from tqdm import tqdm

from ..data.scene import Frame
from ..model.decomposition import otsu_tau
from ..model.gaussians import set_param
from ..model.render import camera_tensors, render_model
from .flow import frame_flows
from .flow_vote import flow_moving, read_frames
from .spawn import SPAWN_LOSS_RATIO, NextFrame, spawn_unexplained


class ScheduleEvents:
    """What `Trainer.after_step` calls at its scheduled iterations; reads the trainer's state
    (`model`, `opt`, `strategy`, `scene`, `cfg`, `flows`, ...) and changes the model in place."""

    def kr_acts(self) -> bool:
        """Whether K.R. shapes the renders now: on, after a decomposition with dynamic Gaussians, and
        the training exposure above 0."""
        m = self.model
        return (
            m.config.kinematic
            and m.decomposed
            and not self.static_only
            and not self.no_decompose
            and self.exposure > 0
            and bool(m.dynamic.any())
        )

    def check_kr(self, it: int) -> None:
        """Measures what K.R.'s blur does to the training renders now and, when it does next to
        nothing (`evaluate.kr_effect_note`), turns K.R. off for the rest of the run. Left alone:
        runs without a decomposition yet, the paper's K.R. form (whose basis would have to be
        re-interpreted), a fitted exposure or camera blur (both ride on K.R.'s blur)."""
        from ..evaluate import kr_effect, kr_effect_note

        m = self.model
        if not self.kr_acts() or m.config.kr_form != "convolve" or self.fitted_exposure is not None or self.camera_motion is not None:
            return
        effect = kr_effect(m, self.scene.train_frames, self.exposure, self.scene.dt)
        note = kr_effect_note(effect)
        self.kr_check = {"iteration": it, "kept": note is None, **effect}
        if note is not None:
            # At exposure 0 the convolve form is the plain deformed covariance: the model renders
            # sharp exactly as before, and the training renders lose a blur they hardly had.
            m.config.kinematic = False
            self.kr_check["note"] = f"K.R. turned off at iteration {it} of {self.cfg.iterations}: {note}"
            if self.progress:
                tqdm.write(f"note: {self.kr_check['note']}")

    def _window_median(self, window: str, start: int | None, nxt: int) -> float | None:
        """The median of the `BUDGET_CHECK_STEPS` steps after `start` once step `nxt` completes
        them (collected in `check_steps[window]`), else None: before, after, or where a run
        resumed inside the window (it skips that check)."""
        from .budget import BUDGET_CHECK_STEPS

        if start is None or not 1 <= nxt - start <= BUDGET_CHECK_STEPS:
            return None
        if nxt - start == 1:
            self.check_steps[window] = []
        steps = self.check_steps.setdefault(window, [])
        steps.append(self.last_step_seconds)
        return statistics.median(steps) if nxt - start == BUDGET_CHECK_STEPS and len(steps) == BUDGET_CHECK_STEPS else None

    def _budget_left(self) -> tuple[float, float]:
        """`(events, seconds)`: the run's time over its steps' so far (the events: densification,
        spawning, decompositions, evaluation, which keep that share of what is left), and the
        seconds left of the time budget, REVISED_HEADROOM of it kept back."""
        from .budget import REVISED_HEADROOM

        return self.train_seconds / max(self.step_seconds, 1e-9), REVISED_HEADROOM * self.cfg.time_budget - self.train_seconds

    def schedule_iteration(self, it: int) -> tuple[float, int]:
        """`(iteration, total)` as the schedules read them: the step itself, or after a time
        budget set the run's length (`watch_tail`: `tail` = (knots, the total planned), each knot
        `(step, schedule position, train seconds)` where it did so), the position running linearly
        between the knots and from the last one to the run's end, which is the planned end; so
        every schedule goes on from where it was and ends where it would have."""
        if self.tail is None:
            return it, self.cfg.iterations
        knots, before = self.tail
        prev: tuple[float, float] = (0, 0.0)
        for at, position, _ in knots:
            if it <= at:
                return prev[1] + (it - prev[0]) * (position - prev[1]) / max(at - prev[0], 1), before
            prev = (at, position)
        return prev[1] + (it - prev[0]) * (before - prev[1]) / max(self.cfg.iterations - prev[0], 1), before

    def watch_budget(self, nxt: int) -> None:
        """Revises the Gaussian budget of a run planned to a time budget from its own steps
        (`budget.refit_gaussian_budget`): the median of the `BUDGET_CHECK_STEPS` steps after
        each of `budget.budget_check_starts` (the first decomposition, each change of image size,
        once more before densification stops; events excluded, as from the pilot's). Each
        revision is recorded in `budget_checks` (run.json)."""
        from .budget import BUDGET_CHECK_STEPS, budget_check_starts, read_budget_pilot, refit_gaussian_budget

        c = self.cfg
        start = next((s for s in budget_check_starts(c) if 1 <= nxt - s <= BUDGET_CHECK_STEPS), None)
        step = self._window_median("budget", start, nxt)
        if step is None:
            return
        n, divisor = len(self.model), self.image_divisor(nxt - 1)
        before = self.strategy.max_gaussians
        pilot_ms = 1000 * read_budget_pilot(c.budget_pilot)[0].at(n, divisor)
        events, left = self._budget_left()
        after, _ = refit_gaussian_budget(c, nxt, n, step, divisor, left / events)
        if divisor > 1:
            # Steps at a smaller image size say little of a full-size step's per-pixel part
            # (docs/method.md, "A time budget"): they may lower the budget, not raise it. The
            # full-size revisions may; time they leave unused buys iterations (`watch_tail`).
            after = min(after, max(before, n))
        self.strategy.max_gaussians = after
        size = "full size" if divisor == 1 else f"1/{divisor} size"
        note = (
            f"Gaussian budget {before:,} -> {after:,} at iteration {nxt}: its steps took {1000 * step:.0f} ms "
            f"at {n:,} Gaussians and {size}, the pilot's {pilot_ms:.0f} ms; {max(left, 0):.0f} s of the budget left, "
            f"events {events - 1:.0%} on top of the steps"
        )
        self.budget_checks.append(
            {
                "iteration": nxt,
                "gaussians": n,
                "divisor": divisor,
                "step_ms": round(1000 * step, 1),
                "pilot_step_ms": round(pilot_ms, 1),
                "events_share": round(events - 1, 3),
                "max_gaussians_before": before,
                "max_gaussians": after,
                "note": note,
            }
        )
        if self.progress:
            tqdm.write(f"note: {note}")

    def watch_tail(self, nxt: int) -> None:
        """Sets a run planned to a time budget to the iterations its time left affords once its
        densification has stopped, more or fewer than planned (`budget.tail_iterations`): first
        from the median of the `BUDGET_CHECK_STEPS` steps after the stop (events at their share
        so far), then every `TAIL_RECHECK_STEPS` from the pace since the last check, events
        included, since steps can grow dearer at a fixed Gaussian count. The schedules' remaining
        stretch is spread over the new length (`schedule_iteration`). Each change is recorded in
        `budget_checks` (run.json)."""
        from .budget import TAIL_RECHECK_STEPS, tail_check_start, tail_iterations

        c = self.cfg
        if self.tail is None:
            step = self._window_median("tail", tail_check_start(c), nxt)
            if step is None:
                return
            events, left = self._budget_left()
            pace, step_ms = step * events, 1000 * step
            how = (
                f"densification has stopped at {len(self.model):,} Gaussians, whose steps took {1000 * step:.0f} ms, "
                f"events {events - 1:.0%} on top"
            )
        else:
            at, _, seconds = self.tail[0][-1]
            if nxt - at < TAIL_RECHECK_STEPS or nxt >= c.iterations:
                return
            _, left = self._budget_left()
            pace = (self.train_seconds - seconds) / (nxt - at)
            step_ms = 1000 * pace
            how = f"the {nxt - at} steps since iteration {at} took {1000 * pace:.0f} ms each, events included"
        total = tail_iterations(c, nxt, pace, left)
        knots, before = self.tail if self.tail is not None else ([], c.iterations)
        self.tail = ([*knots, (nxt, self.schedule_iteration(nxt)[0], self.train_seconds)], before)
        if total == c.iterations:
            return
        note = f"iterations {c.iterations:,} -> {total:,} at iteration {nxt}: {how}; {max(left, 0):.0f} s of the budget left"
        self.budget_checks.append(
            {
                "iteration": nxt,
                "gaussians": len(self.model),
                "step_ms": round(step_ms, 1),
                "iterations_before": c.iterations,
                "iterations": total,
                "note": note,
            }
        )
        c.iterations = total
        if self.progress:
            tqdm.write(f"note: {note}")

    def spawn(self, it: int) -> None:
        """New dynamic Gaussians where the worst-fitted training frames stay unexplained and
        something moves on its own (train/spawn.py). The pixels drawn depend on the seed and the
        iteration only, so that a resumed run spawns as the uninterrupted one would."""
        c, model = self.cfg, self.model
        loss = torch.nan_to_num(self.frame_loss, nan=-1.0)
        seen = loss[loss >= 0]
        if len(seen) == 0:
            return
        # Only frames with a flow to the next one of their camera: without it nothing says what
        # moves on its own, and ungated spawning filled a not-yet-fitted background
        # (docs/real-footage.md, "Spawned Gaussians"). So each camera's last frame gets none.
        has_next = torch.tensor([f.id in self.flows for f in self.scene.train_frames])
        loss = torch.where(has_next, loss, torch.full_like(loss, -1.0))
        # Only frames that fit far worse than the clip's typical one: a scene whose frames all
        # fit about alike gets nothing.
        worst = [
            i for i in torch.argsort(loss, descending=True)[: c.spawn_frames].tolist() if loss[i] > SPAWN_LOSS_RATIO * float(seen.median())
        ]
        for i in worst:
            frame = self.scene.train_frames[i]
            with torch.no_grad():
                out, g = render_model(
                    model,
                    frame.camera,
                    frame.time,
                    self.exposure,
                    self.scene.dt,
                    self.background,
                    velocity=False,
                    world_transform=self.world_transform(frame),
                )
            viewmat, K = camera_tensors(frame.camera)
            added = spawn_unexplained(
                model,
                self.opt,
                self.strategy.state,
                frame.time,
                viewmat,
                K,
                out.image,
                out.depth,
                self.cache.get(frame),
                g.means,
                c.spawn_max,
                c.spawn_life * self.scene.dt,
                np.random.default_rng([c.seed, it, i]),
                self.next_frame(frame, g.means),
            )
            rec = self.spawn_record
            rec["attempts"] += 1
            rec["without_parent"] += added.without_parent
            if added.gaussians:
                rec["added"][frame.id] = rec["added"].get(frame.id, 0) + added.gaussians

    def spawn_summary(self) -> dict:
        """What spawning did, for run.json: `attempts` (frames it looked at), `gaussians` (added
        in all; pruning may have removed some since), `frames` (how many training frames got
        any), `by_time` (normalised time of each such frame -> Gaussians added there, in
        time order: a clip whose late frames never got a turn shows here) and `without_parent`
        (how many of them sit at the rendered depth, no dynamic Gaussian moving like their pixel)."""
        added = self.spawn_record["added"]
        times = {f.id: f.time for f in self.scene.train_frames}
        by_time = {f"{times[k]:.4f}": n for k, n in sorted(added.items(), key=lambda kv: times[kv[0]])}
        return {
            "attempts": self.spawn_record["attempts"],
            "gaussians": sum(added.values()),
            "frames": len(added),
            "by_time": by_time,
            "without_parent": self.spawn_record["without_parent"],
        }

    @torch.no_grad()
    def next_frame(self, frame: Frame, means: torch.Tensor) -> NextFrame:
        """The next frame of `frame`'s camera as spawning reads it (train/spawn.py): its camera,
        the flow to it, and `means` (every Gaussian at `frame`'s time) with the dynamic ones
        moved to its time. `frame` is not its camera's last."""
        j, flow = self.flows[frame.id]
        nxt = self.scene.train_frames[j]
        idx = torch.nonzero(self.model.dynamic).squeeze(1)
        at_next = means.clone()
        at_next[idx] = self.posed(self.model.positions(idx, nxt.time)[0], nxt)
        return NextFrame(*camera_tensors(nxt.camera), flow, at_next, nxt.time)

    def decompose(self) -> None:
        """A static/dynamic decomposition in training: K recomputed, then τ the configured one or
        (tau_auto) the one picked from the distribution of K, never below the configured one.
        Every decomposition also calls dynamic what the optical flow shows moving where K sees no
        motion (train/flow_vote.py; `flow_vote_share` 0 turns that off)."""
        model = self.model
        model.K = model.compute_K()
        tau = otsu_tau(model.K, self.tau_floor, self.cfg.tau_auto_from) if self.cfg.tau_auto else self.tau_floor
        moving = None
        if self.cfg.flow_vote_share > 0:
            start = time.perf_counter()
            by_k = model.dynamic_by_k(tau)
            moving = flow_moving(
                model,
                self.scene.train_frames,
                self.vote_flows(),
                by_k,
                self.cfg.flow_vote_share,
                self.exposure,
                self.scene.dt,
                self.world_transform,
            )
            seconds = time.perf_counter() - start
            if self.flow_vote is None:
                self.flow_vote = {
                    "iteration": self.iteration + 1,
                    "gaussians": int(moving.sum()),
                    "dynamic_by_k": int(by_k.sum()),
                    "later": [],
                    "seconds": 0.0,
                }
            else:
                self.flow_vote["later"].append(int(moving.sum()))
            self.flow_vote["seconds"] = round(self.flow_vote["seconds"] + seconds, 2)
        model.decompose(
            tau, recompute=False, in_place=self.cfg.decompose_in_place, keep_static=not self.cfg.redecompose_to_dynamic, also_dynamic=moving
        )

    def vote_flows(self) -> dict:
        """The flows the decompositions' reading reads: the run's own (flow term or spawning) where they
        are of its method (`flow_vote_method`), else the 16 it reads computed once (whatever
        the clip's length) and kept for the re-decompositions."""
        if self.flows and self.cfg.flow_vote_method == self.cfg.flow_method:
            return self.flows
        if self._vote_flows is None:
            frames = self.scene.train_frames
            self._vote_flows = frame_flows(frames, only={f.id for f in read_frames(frames)}, method=self.cfg.flow_vote_method)
        return self._vote_flows

    @torch.no_grad()
    def importance(self) -> torch.Tensor:
        """Sum over training views of each Gaussian's blending weights (FLoD's importance),
        read off as the gradient of the rendered sum of a constant colour.

        `autograd.grad` with respect to that colour alone: a `.backward()` here left the
        gradient of the rendered sum in the deformation field's `.grad` (and in kappa's), which
        the next optimiser step applied, and which inflated the field's Adam second moments
        by ~1e7 at every level change, all but freezing the field for the rest of the run."""
        model = self.model
        total = torch.zeros(len(model))
        frames = self.scene.train_frames
        pick = np.linspace(0, len(frames) - 1, min(self.cfg.lod_importance_views, len(frames))).round().astype(int)
        for i in sorted(set(pick.tolist())):
            with torch.enable_grad():
                ones = torch.ones(len(model), 1, requires_grad=True)
                out, _ = render_model(
                    model,
                    frames[i].camera,
                    frames[i].time,
                    self.exposure,
                    self.scene.dt,
                    colors=ones,
                    static=self.static_only,
                    velocity=False,
                    world_transform=self.world_transform(frames[i]),
                )
                (grad,) = torch.autograd.grad(out.image.sum(), ones)
            total += grad[:, 0]
        return total

    def next_level(self, level_idx: int) -> None:
        """Ends a FLoD level: prune by importance, keep a snapshot for rendering at that level,
        and clone into the next level with scales re-parameterised so that exp(s) + s_min is
        unchanged."""
        model = self.model
        imp = self.importance()
        keep = imp >= self.cfg.lod_prune_importance
        if keep.sum() >= 4:
            model.keep_gaussians(keep, self.opt, self.strategy.state)
        snap = {
            "params": {k: v.detach().clone() for k, v in model.params.items()},
            **model.per_gaussian.state(),
            "min_scale": model.min_scale,
            "knn": None if model._knn is None else model._knn.clone(),
            "iteration": self.iteration,
        }
        self.levels.append(snap)
        old, new = model.min_scale, self.level_min_scale(level_idx)
        with torch.no_grad():
            s = torch.exp(model.params.log_scales.detach()) + old - new
            model.params = set_param(model.params, self.opt, "log_scales", torch.log(s.clamp_min(1e-8)))
        model.min_scale = new
