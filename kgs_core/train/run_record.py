"""What a training run writes about itself, as methods of `Trainer` (a mixin): checkpoints and
resuming from them, the final model and run.json with the notes a user reads there (why K.R. or
the decomposition did nothing), and the held-out PSNR logged against time with its plot."""

from __future__ import annotations

import math
import random
import time
from pathlib import Path

import numpy as np
import torch

from ..data.scene import Frame, Scene
from ..device import tensors_to
from ..io import atomic_write_text
from ..losses import psnr
from ..migrations import migrate_saved_model
from ..model.decomposition import decomposition_counts
from ..model.dynamic import KinematicsGS
from ..model.render import render_model
from ..run import load_torch, save_decomposition, save_torch, write_run_json
from .budget import read_tail
from .camera_motion import camera_motion_records
from .config import TrainConfig


class ImageCache:
    """Decoded frames as tensors on `device`, loaded once."""

    def __init__(self, device: torch.device | str = "cpu"):
        self.device = torch.device(device)
        self._imgs: dict[tuple[str, str], torch.Tensor] = {}

    def get(self, frame: Frame, kind: str = "image") -> torch.Tensor | None:
        """`kind`: "image" (what the camera recorded), "sharp" (its ground truth) or "mask" (the
        ground-truth dynamic pixels; None when the frame has none)."""
        key = (frame.id, kind)
        if key not in self._imgs:
            arr = {"image": frame.image, "sharp": frame.sharp, "mask": frame.mask}[kind]()
            self._imgs[key] = None if arr is None else torch.from_numpy(arr).to(self.device)
        return self._imgs[key]


def evaluation_frames(scene: Scene, count: int) -> list[tuple[Frame, str]]:
    """Held-out views (sharp) if any; else the training views' sharp ground truth; else the
    training images themselves."""
    if scene.test_frames:
        pool, kind = scene.test_frames, "image"
    elif any(f.sharp_path for f in scene.train_frames):
        pool, kind = [f for f in scene.train_frames if f.sharp_path], "sharp"
    else:
        pool, kind = scene.train_frames, "image"
    idx = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    return [(pool[i], kind) for i in sorted(set(idx.tolist()))]


@torch.no_grad()
def heldout_psnr(model: KinematicsGS, scene: Scene, frames, cache: ImageCache, background, static: bool = False) -> tuple[float, float]:
    """Mean PSNR over the evaluation views, and inside their ground-truth dynamic masks (NaN
    when none of them has a non-empty mask): the quality target's metric, logged over time."""
    vals, dyn = [], []
    for frame, kind in frames:
        out, _ = render_model(model, frame.camera, frame.time, 0.0, scene.dt, background, static=static, velocity=False)
        gt = cache.get(frame, kind)
        vals.append(psnr(out.image, gt))
        mask = cache.get(frame, "mask")
        if mask is not None and mask.any():
            dyn.append(psnr(out.image, gt, mask))
    return float(np.mean(vals)), float(np.mean(dyn)) if dyn else float("nan")


def kr_note(cfg: TrainConfig, exposure: float) -> str | None:
    """Why the kinematic blur (K.R.) does nothing in this run, or None when it acts."""
    if not cfg.model.kinematic or "deform" in cfg.ablate:
        return None
    if exposure <= 0:
        return (
            "exposure 0: K.R. has no blur to model and only adds cost (the scene's frames say exposure 0; "
            "give the video's with --exposure, e.g. 0.5)"
        )
    return None


# Below this share of dynamic Gaussians the run says that its moving objects, if any, render
# static: a scene whose moving object neither K nor the flow's reading found ends with almost
# nothing dynamic, far under what scenes with a followed object end with (docs/method.md,
# "The motion probe").
DECOMPOSITION_NOTE_SHARE = 0.01


def decomposition_note(dynamic_share: float, tau: float, decompose_at: int) -> str | None:
    """What to tell the user when the decomposition called (almost) nothing dynamic: right for a static
    scene, and the way a moving object whose motion neither the field (by the first decomposition) nor
    the flow's reading showed gets lost (it then renders static, a ghost or nothing)."""
    if dynamic_share >= DECOMPOSITION_NOTE_SHARE:
        return None
    return (
        f"the decomposition called {dynamic_share:.2%} of the Gaussians dynamic (K under tau {tau:.3g} almost everywhere). "
        f"In a static scene that is right; if something moves, the field had not learned its motion by the "
        f"first decomposition (iteration {decompose_at}), the optical flow did not show it either, and it renders "
        f"static: retrain with a later decomposition "
        f"(--set decompose_at=N) or --ablate decompose"
    )


def plot_psnr_vs_time(rows: list[dict], path: Path, title: str = "", label: str = "held-out PSNR") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..io import atomic_write_bytes

    rows = [r for r in rows if not math.isnan(r["psnr_heldout"])]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=110)
    ax.plot([r["train_seconds"] for r in rows], [r["psnr_heldout"] for r in rows], marker="o", ms=3, label=label)
    dyn = [r for r in rows if not math.isnan(r.get("psnr_heldout_dynamic", float("nan")))]
    if dyn:
        ax.plot(
            [r["train_seconds"] for r in dyn], [r["psnr_heldout_dynamic"] for r in dyn], marker="o", ms=3, label="inside the dynamic mask"
        )
        ax.legend(fontsize=7)
    ax.set_xlabel("training time (s)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


class RunRecord:
    """The held-out log, checkpoints, `restore` and the final save of `Trainer`."""

    def wall_seconds(self) -> float:
        """Wall time spent on this run, the time before a resume included."""
        return time.time() - self.wall_start

    def log(self, it: int, loss: float) -> dict:
        p, p_dyn = heldout_psnr(self.model, self.scene, self.eval_set, self.cache, self.background, static=self.static_only)
        counts = decomposition_counts(self.model, self.static_only)
        row = {
            "iteration": it,
            "train_seconds": round(self.train_seconds, 3),
            "wall_seconds": round(self.wall_seconds(), 3),
            "loss": loss,
            "psnr_heldout": p,
            "psnr_heldout_dynamic": p_dyn,
            "gaussians": counts["gaussians"],
            "dynamic_share": counts["dynamic_share"],
            "exposure": round(self.exposure, 5),
        }
        self.log_rows.append(row)
        head = list(row)
        # (.get: rows read back from a log written before a column existed, on resume)
        text = ",".join(head) + "\n" + "\n".join(",".join(f"{r.get(k, float('nan'))}" for k in head) for r in self.log_rows) + "\n"
        atomic_write_text(self.run_dir / "log.csv", text)
        if self.on_log:
            self.on_log(row)
        return row

    def log_progress(self, bar, loss: float) -> None:
        row = self.log(self.iteration, loss)
        bar.set_postfix(
            loss=f"{loss:.4f}", psnr=f"{row['psnr_heldout']:.2f}", gaussians=row["gaussians"], dynamic=f"{row['dynamic_share']:.0%}"
        )

    def checkpoint(self) -> Path:
        path = self.run_dir / "checkpoints" / f"ckpt_{self.iteration:06d}.pt"
        save_torch(
            path,
            {
                "iteration": self.iteration,
                "train_seconds": self.train_seconds,
                "step_seconds": self.step_seconds,
                "wall_seconds": self.wall_seconds(),
                "model": self.model.state(),
                "opt": self.opt.state_dict(),
                "net_opt": self.net_opt.state_dict(),
                "levels": self.levels,
                "log": self.log_rows,
                "rng": {"torch": torch.get_rng_state(), "python": random.getstate()},
                "strategy": dict(self.strategy.state),
                "camera_motion": None if self.camera_motion is None else self.camera_motion.state_dict(),
                "pose_correction": None if self.pose_correction is None else self.pose_correction.state_dict(),
                "frame_loss": self.frame_loss.clone(),
                "fitted_exposure": None if self.fitted_exposure is None else self.fitted_exposure.state_dict(),
                "kr_check": self.kr_check,
                "budget_checks": self.budget_checks,
                "max_gaussians": self.strategy.max_gaussians,
                "iterations": self.cfg.iterations,
                "tail": self.tail,
                "flow_vote": self.flow_vote,
                "spawn_record": self.spawn_record,
            },
        )
        return path

    def restore(self, path: Path) -> None:
        state = tensors_to(migrate_saved_model(load_torch(path)), self.device)
        self.model = KinematicsGS.from_state(state["model"])
        if self.camera_motion is not None and state.get("camera_motion") is not None:
            self.camera_motion.load_state_dict(state["camera_motion"])
        if self.pose_correction is not None and state.get("pose_correction") is not None:
            self.pose_correction.load_state_dict(state["pose_correction"])
        if self.fitted_exposure is not None and state.get("fitted_exposure") is not None:
            self.fitted_exposure.load_state_dict(state["fitted_exposure"])
            self.exposure = float(self.fitted_exposure)
        self.make_optimizers()
        self.opt.load_state_dict(state["opt"])
        self.net_opt.load_state_dict(state["net_opt"])
        self.strategy = self.make_strategy()
        self.strategy.state.update(grad_sum=state["strategy"]["grad_sum"], count=state["strategy"]["count"])
        self.iteration = state["iteration"]
        self.train_seconds = state["train_seconds"]
        self.step_seconds = state.get("step_seconds", self.train_seconds)  # (absent from older checkpoints)
        self.levels = state["levels"]
        self.log_rows = state["log"]
        # The wall time a resume continues from: the checkpoint's own (checkpoints of older
        # runs kept only their last log row's, which lost the time from that row to the save).
        self.resumed_wall_seconds = state.get("wall_seconds", self.log_rows[-1]["wall_seconds"] if self.log_rows else 0.0)
        if state.get("frame_loss") is not None and len(state["frame_loss"]) == len(self.frame_loss):
            self.frame_loss = state["frame_loss"].clone()  # (absent from checkpoints of older runs)
        self.kr_check = state.get("kr_check")
        # (Absent from older checkpoints.) A revised budget is the strategy's from then on.
        self.budget_checks = state.get("budget_checks") or []
        self.strategy.max_gaussians = state.get("max_gaussians", self.strategy.max_gaussians)
        # A run whose length its time budget set goes on to that count, on the same schedules.
        self.tail = read_tail(state.get("tail"), self.train_seconds)
        self.cfg.iterations = int(state.get("iterations", self.cfg.iterations))
        self.flow_vote = state.get("flow_vote")  # (absent from older checkpoints)
        self.spawn_record = {
            "attempts": 0,
            "added": {},
            "without_parent": 0,  # (older checkpoints lack some)
            **(state.get("spawn_record") or {}),
        }
        torch.set_rng_state(state["rng"]["torch"])
        random.setstate(state["rng"]["python"])

    def save_final(self, info: dict) -> None:
        dropped_kr = self.kr_check is not None and not self.kr_check["kept"]
        if dropped_kr:
            # Trained without K.R. since the check, saved with it: at exposure 0 it renders the
            # same, and the viewers read its velocities (ellipsoids, the exposure slider).
            self.model.config.kinematic = True
        counts = decomposition_counts(self.model, self.static_only)
        save_torch(self.run_dir / "model.pt", {"model": self.model.state(), "levels": self.levels})
        save_decomposition(self.run_dir, self.model.K)
        plot_psnr_vs_time(self.log_rows, self.run_dir / "psnr_vs_time.png", title=self.scene.name)
        if info["status"] == "training":
            info["status"] = "done"
        info["config"]["iterations"] = self.cfg.iterations  # (a time budget may have changed it: `watch_tail`)
        info.update(
            iteration=self.iteration,
            train_seconds=round(self.train_seconds, 2),
            lod_levels=len(self.levels) + 1,
            final_psnr_heldout=self.log_rows[-1]["psnr_heldout"] if self.log_rows else None,
            **counts,
        )
        if self.model.decomposed and not self.static_only and not self.no_decompose:
            tau = self.model.config.tau
            info["tau"] = tau
            info["tau_choice"] = (
                f"picked from the distribution of K (Otsu on log10 K), not below {self.tau_floor:.3g}"
                if self.cfg.tau_auto and tau > self.tau_floor
                else f"the configured {tau:.3g}"
            )
            note = decomposition_note(counts["dynamic_share"], tau, self.cfg.decompose_at)
            if note:
                info["decomposition_note"] = note
                if self.progress:
                    print(f"note: {note}")
        if self.pose_correction is not None:
            info["pose_refine"] = self.pose_correction.summary()
        if self.camera_motion is not None:
            info["camera_motion"] = camera_motion_records(self.camera_motion, self.scene.train_frames)
        if self.fitted_exposure is not None:
            info["exposure"] = self.exposure
            info["exposure_choice"] = f"fitted to the footage from {self.fitted_exposure.start:g}"
        if self.events:
            info["guard_events"] = self.events
        if self.budget_checks:
            info["budget_checks"] = self.budget_checks
        if self.cfg.spawn_frames > 0 and not self.static_only:
            info["spawn"] = self.spawn_summary()
        if self.flow_vote is not None:
            info["flow_vote"] = self.flow_vote
        self.measure_kr(info, dropped_kr)
        write_run_json(self.run_dir, info)

    def measure_kr(self, info: dict, dropped: bool) -> None:
        """What K.R. did: the mid-run check's record (`kr_check`; its note when it turned K.R.
        off), and at the end of a run that trained with K.R. throughout, its effect on the
        training renders (`evaluate.kr_effect`), with a note when it does next to nothing, so
        that a clip whose blur the method cannot use shows in the run instead of costing time
        silently."""
        from ..evaluate import kr_effect, kr_effect_note

        if self.kr_check is not None:
            info["kr_check"] = {k: v for k, v in self.kr_check.items() if k != "note"}
            if dropped:
                info["kr_note"] = self.kr_check["note"]
                return
        if not self.kr_acts():
            return
        motion = None if self.camera_motion is None else (lambda f: self.camera_motion.get(f.id))
        info["kr_effect"] = kr_effect(self.model, self.scene.train_frames, self.exposure, self.scene.dt, camera_motion=motion)
        note = kr_effect_note(info["kr_effect"])
        if note:
            info["kr_note"] = note
            if self.progress:
                print(f"note: {note}")
