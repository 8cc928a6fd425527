"""The training loop: data, schedules, losses, densification, decomposition, FLoD levels,
held-out PSNR against wall time, checkpoints and resume."""

from __future__ import annotations

import dataclasses
import math
import os
import random
import time
import traceback
from pathlib import Path
from typing import Callable, Iterator

import torch
from tqdm import tqdm

from ..data.scene import Frame, Scene
from ..device import computing_on, resolve_device
from ..io import atomic_write_text
from ..model.deformation import TimeNoise
from ..model.dynamic import KinematicsGS
from ..model.gaussians import init_from_points, make_optimizer, random_points
from ..run import write_run_json
from .camera_motion import CameraMotion
from .config import TrainConfig
from .densify import DensifyStrategy
from .events import ScheduleEvents
from .exposure import FittedExposure
from .flow import frame_flows
from .image_levels import LevelViews, image_divisor
from .objective import Objective
from .pose_refine import PoseCorrection
from .run_record import ImageCache, RunRecord, evaluation_frames, kr_note


class NonFiniteError(FloatingPointError):
    """A loss or gradient became NaN/Inf; the message names the tensor and the iteration."""


def lr_exp(k: int, total: int, lr0: float, lr1: float) -> float:
    f = min(max(k / max(total, 1), 0.0), 1.0)
    return math.exp(math.log(lr0) * (1 - f) + math.log(lr1) * f)


def check_finite(it: int, **tensors) -> None:
    for name, t in tensors.items():
        if t is not None and not torch.isfinite(t).all():
            raise NonFiniteError(f"non-finite values in {name} at iteration {it}")


# The time window (`time_window_start`) covers the whole clip at this fraction of the warm-up,
# so that the field sees every frame for the warm-up's last quarter before K is computed: with
# the window ending at the decomposition itself, the sheet's decomposition IoU fell from 0.95 to 0.8.
WINDOW_FULL_AT = 0.75


class Trainer(Objective, ScheduleEvents, RunRecord):
    """One training run of a scene: `run()` (or `iterate()`, a step at a time). The loss is
    `Objective`'s (train/objective.py), the schedule's events `ScheduleEvents`'
    (train/events.py), the held-out log, checkpoints and the final save `RunRecord`'s
    (train/run_record.py)."""

    def __init__(
        self,
        scene: Scene,
        run_dir: str | Path,
        cfg: TrainConfig,
        progress: bool = True,
        on_log: Callable[[dict], None] | None = None,
        should_stop: Callable[[], bool] | None = None,
        on_step: Callable[[int, float], None] | None = None,
        threads=None,
    ):
        # First, so that a device this machine lacks fails before anything is read or written.
        self.device = resolve_device(cfg.device, "device")
        self.scene, self.cfg = scene, cfg
        self.threads = threads  # a kgs_core.threads.ThreadTuner, or None (the count stays as it is)
        self.run_dir = Path(run_dir)
        self.progress, self.on_log, self.should_stop, self.on_step = progress, on_log, should_stop, on_step
        self.lr_scale = 1.0  # lowered by NaN recoveries (on_nonfinite = "restore")
        # Called with "forward", "backward", "optimiser" as each phase of a step ends (`bench step`).
        self.on_phase: Callable[[str], None] | None = None
        self.restores = 0
        self.events: list[dict] = []
        self.background = torch.zeros(3, device=self.device)
        self.cache = ImageCache(self.device)
        self.eval_set = evaluation_frames(scene, cfg.eval_frames)
        self.iteration = 0
        self.train_seconds = 0.0
        self.resumed_wall_seconds = 0.0  # restore: where the wall clock of a resumed run starts
        self.wall_start = time.time()  # iterate sets it again, less the resumed time
        self.info: dict | None = None  # the run's info, set when training ends
        self.levels: list[dict] = []
        self.log_rows: list[dict] = []
        n_levels = max(1, cfg.lod_levels)
        fr = list(cfg.lod_fractions)[-n_levels:] if n_levels > 1 else [1.0]
        self.level_ends = [int(round(f * cfg.iterations)) for f in fr]
        self.noise = TimeNoise(
            cfg.noise_init_frames * scene.dt,
            cfg.noise_final_frames * scene.dt,
            int(cfg.noise_until * cfg.iterations),
            int(cfg.noise_delay * cfg.iterations),
            cfg.noise_w_delay,
        )
        # The exposure K.R. models: the config's when given (`--exposure`), else the scene's.
        self.exposure = scene.exposure if cfg.exposure is None else float(cfg.exposure)
        # fit_exposure: learned from there (`self.exposure` follows it after each step).
        self.fitted_exposure = FittedExposure(self.exposure) if cfg.fit_exposure else None
        if self.fitted_exposure is not None:
            self.exposure = float(self.fitted_exposure)  # (a start of 0 or 1 is clipped: START_RANGE)
        # The configured τ, before any decomposition writes its own into the model's config.
        self.tau_floor = cfg.model.tau
        self.static_only = "deform" in cfg.ablate
        self.no_decompose = "decompose" in cfg.ablate
        self.camera_motion = CameraMotion(scene.train_frames, learned=cfg.camera_blur == "learned") if cfg.camera_blur != "off" else None
        self.pose_correction = PoseCorrection(scene.train_frames) if cfg.pose_refine else None
        # lambda_flow: each training frame's flow to the next of its camera (train/flow.py).
        # (Also what spawning reads: where something moves on its own, train/spawn.py.)
        self.flows = (
            frame_flows(scene.train_frames, method=cfg.flow_method)
            if (cfg.lambda_flow > 0 or cfg.spawn_frames > 0) and not self.static_only
            else {}
        )
        self.flows = {fid: (j, flow.to(self.device)) for fid, (j, flow) in self.flows.items()}
        for module in (self.camera_motion, self.pose_correction, self.fitted_exposure):
            if module is not None:
                module.to(self.device)
        self.views = LevelViews(self.cache, self.flows)
        self.divisor_override: int | None = None  # every step at this image divisor (the budget's pilot)
        # Running photometric loss per training frame (frame_sampling "loss"); NaN: not yet seen.
        self.frame_loss = torch.full((len(scene.train_frames),), float("nan"), device=self.device)
        # What the mid-run check of K.R. measured and decided (`check_kr`); None until it ran.
        self.kr_check: dict | None = None
        # A time budget's revisions from the run's own steps (`watch_budget`), and the step
        # times the next one reads.
        self.budget_checks: list[dict] = []
        self.check_steps: dict[str, list[float]] = {}  # the steps a budget check reads (`_window_median`)
        # (knots (step, schedule position, train seconds), planned total) once `watch_tail` has set the run's length
        self.tail: tuple[list[tuple[int, float, float]], int] | None = None
        self.last_step_seconds = 0.0
        self.step_seconds = 0.0  # the steps' share of `train_seconds` (the rest: events)
        # What the decompositions' reading of the flow added to the dynamic set (`split`); None until the
        # first decomposition. `_vote_flows`: the flows it reads where the run has none of its own.
        self.flow_vote: dict | None = None
        self._vote_flows: dict | None = None
        # Spawning's record for run.json (`spawn_summary`): the frames it tried, the Gaussians
        # it added to each training frame (by frame id), and how many of them had no parent.
        self.spawn_record: dict = {"attempts": 0, "added": {}, "without_parent": 0}

    # ------------------------------------------------------------ setup

    def init_model(self) -> None:
        cfg, scene = self.cfg, self.scene
        torch.manual_seed(cfg.seed)
        random.seed(cfg.seed)
        if cfg.init_from:
            self.init_from_run(Path(cfg.init_from))
            return
        pts, cols = scene.points, scene.point_colors
        if len(pts) < 4:
            pts, cols = random_points(cfg.init_points, 1.0, cfg.seed)
        params = init_from_points(pts, cols, cfg.model.sh_degree, cfg.model.feature_dim, cfg.init_points, cfg.seed).to(self.device)
        self.model = KinematicsGS(params.requires_grad_(True), cfg.model)
        self.model.min_scale = self.level_min_scale(0)
        self.make_optimizers()
        self.strategy = self.make_strategy()

    def init_from_run(self, parent: Path) -> None:
        """Fine-tuning: the parent run's final model, decomposed at this config's τ, then trained as
        it is."""
        from ..run import load_run

        model = load_run(parent, self.device).model
        # Decomposed at this config's τ: from the stored K, or (a parent stopped before its decomposition)
        # from K computed now.
        model.decompose(self.cfg.model.tau, recompute=not model.decomposed, in_place=self.cfg.decompose_in_place)
        model.params.requires_grad_(True)
        model.train()
        self.model = model
        self.make_optimizers()
        self.strategy = self.make_strategy()

    def level_min_scale(self, level_idx: int) -> float:
        """FLoD lower bound of level `level_idx` (0-based): lambda * rho^l below the top level,
        0 at it. (The paper writes rho^(1-l) with rho in (0, 1), which grows with l; the intent,
        coarse to fine, is a geometric decay, so we use rho^(l-1) with rho in (0, 1).)"""
        n = len(self.level_ends)
        if level_idx >= n - 1:
            return 0.0
        return self.cfg.lod_lambda * self.cfg.lod_rho**level_idx

    def make_strategy(self) -> DensifyStrategy:
        return dataclasses.replace(self.cfg.densify)  # this run's own copy, with fresh statistics

    def make_optimizers(self) -> None:
        c = self.cfg
        lrs = {
            "means": c.lr_means,
            "quats": c.lr_quats,
            "log_scales": c.lr_scales,
            "opacity_logits": c.lr_opacity,
            "sh0": c.lr_sh0,
            "sh_rest": c.lr_sh_rest,
            "features": c.lr_features,
        }
        self.opt = make_optimizer(self.model.params, lrs)
        nets = self.model.network_parameters()
        self.net_opt = torch.optim.Adam(
            [
                {"params": nets["grid"], "lr": c.lr_grid, "name": "grid"},
                {"params": nets["deform_mlp"] + nets["fine_mlp"], "lr": c.lr_deform, "name": "mlp"},
                {"params": nets["kappa"], "lr": c.lr_kappa, "name": "kappa"},
            ]
            + (
                [{"params": [self.camera_motion.motion], "lr": c.lr_camera_motion, "name": "camera_motion"}]
                if c.camera_blur == "learned"
                else []
            )
            + ([{"params": [self.pose_correction.delta], "lr": c.lr_pose, "name": "pose"}] if self.pose_correction is not None else [])
            + (
                [{"params": [self.fitted_exposure.logit], "lr": c.lr_exposure, "name": "exposure"}]
                if self.fitted_exposure is not None
                else []
            ),
            eps=1e-15,
            fused=True,
        )

    def set_learning_rates(self, it: int) -> None:
        """Schedules (exponential decay) times `lr_scale` (lowered by each NaN recovery)."""
        c = self.cfg
        schedules = {
            "means": (c.lr_means, c.lr_means_final),
            "grid": (c.lr_grid, c.lr_grid_final),
            "mlp": (c.lr_deform, c.lr_deform_final),
            "pose": (c.lr_pose, c.lr_pose_final),
        }
        for g in [*self.opt.param_groups, *self.net_opt.param_groups]:
            g.setdefault("base_lr", g["lr"])
            if g["name"] in schedules:
                lr = lr_exp(*self.schedule_iteration(it), *schedules[g["name"]])
            else:
                lr = g["base_lr"]
            g["lr"] = lr * self.lr_scale

    # ------------------------------------------------------------ one step

    def world_transform(self, frame: Frame):
        """The training frame's pose correction as a rigid motion of the Gaussians (None when
        poses are not refined)."""
        return None if self.pose_correction is None else self.pose_correction.world_transform(frame)

    def posed(self, x: torch.Tensor, frame: Frame) -> torch.Tensor:
        """World positions `x` (N, 3) under `frame`'s pose correction, as its render draws them."""
        moved = self.world_transform(frame)
        return x if moved is None else x @ moved[0].T + moved[1]

    def pick_frames(self, k: int, it: int = 0) -> list[int]:
        """Indices of the `k` training frames step `it` sees: within the warm-up's time window
        (`time_window_start`) when one is set, else all frames, uniformly or weighted by their
        running loss (`frame_sampling`)."""
        c = self.cfg
        frames = self.scene.train_frames
        n = len(frames)
        if c.time_window_start < 1.0:
            grow = min(1.0, it / max(1.0, WINDOW_FULL_AT * c.decompose_at))
            half = 0.5 * (c.time_window_start + (1.0 - c.time_window_start) * grow)  # of the clip
            t0, t1 = min(f.time for f in frames), max(f.time for f in frames)
            mid, span = 0.5 * (t0 + t1), max(t1 - t0, 1e-9)
            inside = [i for i, f in enumerate(frames) if abs(f.time - mid) <= half * span + 1e-9]
            if k <= len(inside) < n:
                return random.sample(inside, k)
        if c.frame_sampling == "uniform" or torch.isnan(self.frame_loss).any():
            return random.sample(range(n), k)
        p = (1 - c.frame_sampling_mix) / n + c.frame_sampling_mix * self.frame_loss / self.frame_loss.sum()
        return [int(i) for i in torch.multinomial(p, k, replacement=False)]

    def image_divisor(self, it: int) -> int:
        """The training images' size divisor at step `it` (`downscales`, train/image_levels.py)."""
        if self.divisor_override is not None:
            return self.divisor_override
        c = self.cfg
        at, total = self.schedule_iteration(it)
        return image_divisor(int(at), total, c.downscales, c.downscale_until)

    def train_step(self, it: int) -> float:
        c = self.cfg
        self.set_learning_rates(it)
        picks = self.pick_frames(min(c.batch_size, len(self.scene.train_frames)), it)
        total = 0.0
        outs = []
        phase = self.on_phase
        for i in picks:
            frame = self.scene.train_frames[i]
            loss, out = self.loss_for(frame, it)
            check_finite(it, loss=loss)
            value = float(loss.detach())
            seen = self.frame_loss[i]
            self.frame_loss[i] = value if torch.isnan(seen) else 0.7 * float(seen) + 0.3 * value
            if phase:
                phase("forward")
            (loss / len(picks)).backward()
            self.check_gradients(it)
            if phase:
                phase("backward")
            total += value / len(picks)
            outs.append(out)
        # (check_gradients after the last backward has seen every accumulated gradient.)
        for out in outs:
            self.strategy.accumulate(out, out.image.shape[1], out.image.shape[0])
        self.opt.step()
        self.net_opt.step()
        self.opt.zero_grad(set_to_none=True)
        self.net_opt.zero_grad(set_to_none=True)
        if self.fitted_exposure is not None:
            self.exposure = float(self.fitted_exposure)
        if phase:
            phase("optimiser")
        return total

    # ------------------------------------------------------------ schedule events

    def after_step(self, it: int) -> None:
        c, model = self.cfg, self.model
        nxt = it + 1
        # Every event of this count reads the model its iterations trained, so the opacity reset
        # comes last: the paper preset's first FLoD level ends at its reset (3,000), and after
        # the reset the level-1 snapshot had every opacity at 0.01 and its importance prune read
        # a near-empty render; spawning, on a densification count that is also the reset's,
        # would render it too. A level also ends before densification adds to it.
        if nxt in self.level_ends[:-1]:
            self.next_level(self.level_ends.index(nxt) + 1)
        changed = self.strategy.step(model, self.opt, nxt)
        total = self.schedule_iteration(nxt)[1]  # (the planned count, also after a time budget changed the run's length)
        if changed and c.spawn_frames > 0 and model.decomposed and not self.static_only and nxt >= c.spawn_from * total:
            self.spawn(nxt)
        if not self.static_only and not self.no_decompose:
            if nxt == c.decompose_at or (
                model.decomposed and c.decompose_every and nxt > c.decompose_at and (nxt - c.decompose_at) % c.decompose_every == 0
            ):
                self.decompose()
        if 0 < c.kr_check_at < 1 and nxt == max(1, round(c.kr_check_at * total)):
            self.check_kr(nxt)
        if c.budget_pilot and c.time_budget > 0 and model.decomposed:
            self.watch_budget(nxt)
        if c.budget_pilot and c.time_budget > 0:
            self.watch_tail(nxt)
        self.strategy.reset_opacities(model, self.opt, nxt)

    # ------------------------------------------------------------ guards

    def check_gradients(self, it: int) -> None:
        """NaN/Inf in any gradient: an error naming the parameter (a Gaussian attribute, a
        network weight, the camera motion, a pose correction or the fitted exposure) and the
        iteration."""
        named = {f"gaussians.{k}": v for k, v in self.model.params.items()}
        named.update({f"network.{k}": p for k, p in self.model.named_parameters()})
        for part, module in (("camera_motion", self.camera_motion), ("pose_correction", self.pose_correction)):
            if module is not None:
                named.update({f"{part}.{k}": p for k, p in module.named_parameters()})
        if self.fitted_exposure is not None:
            named["exposure.logit"] = self.fitted_exposure.logit
        grads = [p.grad for p in named.values() if p.grad is not None]
        # One sum per tensor (NaN and Inf propagate into it) instead of an isfinite mask each:
        # the names are looked up only when something is wrong.
        if not grads or bool(torch.isfinite(torch.stack([g.sum() for g in grads])).all()):
            return
        for name, p in named.items():
            if p.grad is not None and not torch.isfinite(p.grad).all():
                bad = int((~torch.isfinite(p.grad)).sum())
                raise NonFiniteError(f"non-finite gradient of {name} ({bad} values) at iteration {it}")

    def recover(self, exc: "NonFiniteError") -> None:
        """`on_nonfinite = "restore"`: reload the newest checkpoint and lower every learning rate."""
        ckpts = sorted((self.run_dir / "checkpoints").glob("ckpt_*.pt"))
        if not ckpts or self.restores >= self.cfg.nonfinite_max_restores:
            raise exc
        self.restores += 1
        self.lr_scale *= self.cfg.nonfinite_lr_factor
        self.restore(ckpts[-1])
        self.events.append({"iteration": self.iteration, "event": "restored", "reason": str(exc), "lr_scale": self.lr_scale})
        if self.progress:
            print(f"{exc}: restored {ckpts[-1].name}, learning rates x{self.lr_scale:g}")

    # ------------------------------------------------------------ the loop

    def run(self, resume: bool = False) -> dict:
        """Trains to the configured iteration count (or to where `should_stop` says) and
        returns the run's info (also written to run.json)."""
        for _ in self.iterate(resume):
            pass
        return self.info

    def iterate(self, resume: bool = False) -> Iterator[int]:
        """`run` one iteration at a time: yields the iteration count after each step, so that
        a caller can step several trainers in turn (the benchmarks' `interleave`). `self.info` holds the
        run's info when the generator is exhausted."""
        cfg = self.cfg
        self.run_dir.mkdir(parents=True, exist_ok=True)
        ckpts = sorted((self.run_dir / "checkpoints").glob("ckpt_*.pt"))
        with computing_on(self.device):  # (tensors made without a device land on the run's)
            if resume and ckpts:
                self.restore(ckpts[-1])
            else:
                self.init_model()
        scene_root = Path(self.scene.root).resolve()
        # The scene both as an absolute path (for people) and relative to the run (what a
        # copied or moved workspace, or data folder, still finds): `LoadedRun.scene_path`.
        info = {
            "status": "training",
            "scene": str(scene_root),
            "scene_from_run": os.path.relpath(scene_root, self.run_dir.resolve()),
            "scene_name": self.scene.name,
            "config": cfg.to_dict(),
            "normalization": self.scene.normalization.to_dict(),
            "exposure": self.exposure,
            "dt": self.scene.dt,
            "frames": len(self.scene.frames),
            "image_size": [self.scene.frames[0].camera.width, self.scene.frames[0].camera.height],
        }
        note = kr_note(cfg, self.exposure)
        if note:
            info["kr_note"] = note
            if self.progress:
                print(f"note: {note}")
        write_run_json(self.run_dir, info)
        (self.run_dir / "error.txt").unlink(missing_ok=True)
        # Set once: restoring a checkpoint after a non-finite step (`recover`) keeps the clock.
        self.wall_start = time.time() - self.resumed_wall_seconds
        with computing_on(self.device):
            if cfg.on_nonfinite == "restore" and not ckpts:
                self.checkpoint()  # a good state to fall back to before the first scheduled checkpoint
            if not self.log_rows:
                self.log(0, float("nan"))
        bar = tqdm(total=cfg.iterations, initial=self.iteration, disable=not self.progress, desc="train", unit="it", dynamic_ncols=True)
        loss = float("nan")
        try:
            while self.iteration < cfg.iterations:
                if self.should_stop and self.should_stop():
                    info["status"] = "cancelled"
                    break
                with computing_on(self.device):
                    t0 = time.perf_counter()
                    try:
                        loss = self.train_step(self.iteration)
                    except NonFiniteError as exc:
                        if cfg.on_nonfinite != "restore":
                            raise
                        self.recover(exc)
                        continue
                    self.last_step_seconds = time.perf_counter() - t0
                    if self.threads is not None:
                        self.threads.observe(self.last_step_seconds)
                    self.iteration += 1
                    self.train_seconds += self.last_step_seconds
                    self.step_seconds += self.last_step_seconds
                    # Logged before the events scheduled at this count (densification, an opacity
                    # reset, a decomposition, a FLoD level change), so that the row scores what the
                    # iterations trained: after them, the paper preset's opacity reset at 3,000
                    # (every opacity capped at 0.01) logged a near-empty render. The
                    # last row comes after them: it scores the model that is saved.
                    last = self.iteration == cfg.iterations
                    if self.iteration % cfg.eval_every == 0 and not last:
                        self.log_progress(bar, loss)
                    t0 = time.perf_counter()
                    self.after_step(self.iteration - 1)
                    self.train_seconds += time.perf_counter() - t0
                    if last:
                        self.log_progress(bar, loss)
                    if self.iteration % cfg.checkpoint_every == 0:
                        self.checkpoint()
                    if self.on_step:
                        self.on_step(self.iteration, loss)
                if bar.total != cfg.iterations:  # (a time budget changed the run's length: `watch_tail`)
                    bar.total = cfg.iterations
                bar.update(1)
                yield self.iteration
        except Exception as exc:
            atomic_write_text(self.run_dir / "error.txt", f"{type(exc).__name__}: {exc}\n\n{traceback.format_exc()}")
            info.update(status="failed", error=f"{type(exc).__name__}: {exc}", iteration=self.iteration)
            write_run_json(self.run_dir, info)
            raise
        finally:
            bar.close()
        with computing_on(self.device):
            self.checkpoint()
            self.save_final(info)
        self.info = info


def train(scene: Scene, run_dir: str | Path, cfg: TrainConfig, resume: bool = False, progress: bool = True, **kw) -> dict:
    return Trainer(scene, run_dir, cfg, progress=progress, **kw).run(resume=resume)
