"""Probe: how far a synthetic scene's rigid moving object (`die`, `spin`, `top`, `swing`) gets when its Gaussians
move rigidly, by the ground truth or by a learned per-frame rigid motion, everything else being
the full method (fast preset). It answers "is the motion what loses the object, and can a rigid
representation learn it from the photometric loss" (docs/method.md, "The motion probe").

A probe, not a feature: it patches `KinematicsGS.offsets_at`, `Trainer.init_model`,
`Trainer.pick_frames` and `Trainer.loss_for` in this process only. The object's Gaussians are
found and put in the object's pose at time 0 from the generator's ground truth in every mode, so
the grouping is given and only the motion differs:

- `oracle`: the object's Gaussians follow the true rigid motion.
- `rigid`: they follow one learned rigid motion, a rotation vector and a translation per frame
  (linear between frames), frame 0 fixed at identity; with `--window`, training sees a time
  window grown from the first frame over `--window` of the run, each frame beyond it started at
  constant velocity from the last two inside; `--smooth` weighs the squared second difference
  of the per-frame motion.

    python scripts/probe_rigid_motion.py die SCENE_DIR RUN_DIR --motion rigid --window 0.4 --smooth 1 [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import random

import numpy as np
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from kgs_app.cli_args import setting
from kgs_core.data.formats import load_scene
from kgs_core.data.synth.scenes import build_world
from kgs_core.evaluate import evaluate_model, render_at
from kgs_core.model.deformation import Offsets
from kgs_core.model.dynamic import KinematicsGS
from kgs_core.model.kinematics import so3_exp
from kgs_core.render.covariance import normalize_quats, quat_to_rotmat
from kgs_core.run import load_run
from kgs_core.train.config import make_config
from kgs_core.train.trainer import Trainer

OBJECT_MARGIN = 1.05  # a Gaussian belongs to the object when inside its box grown by this


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_name", choices=["die", "spin", "top", "swing"])
    ap.add_argument("scene_dir")
    ap.add_argument("run_dir")
    ap.add_argument("--motion", choices=["oracle", "rigid"], default="oracle")
    ap.add_argument("--window", type=float, default=0.0, help="share of the run over which the time window grows (0: none)")
    ap.add_argument("--smooth", type=float, default=0.0, help="weight of the per-frame motion's second difference")
    ap.add_argument("--lr", default="3e-2,3e-3", help="learning rates of the rotations and translations")
    ap.add_argument("--iterations", type=int, default=1500)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        type=setting,
        help="a training setting, as kgs-app train --set (repeatable)",
    )
    ap.add_argument("--seed", type=int, default=0, help="training seed, and the seed the scene was synthesized with")
    args = ap.parse_args()
    torch.set_num_threads(2)
    scene = load_scene(args.scene_dir)
    scale, centre = float(scene.normalization.scale), np.asarray(scene.normalization.center, float)
    world = build_world(args.scene_name, args.seed)
    obj = next(o for o in world.objects if o.dynamic)
    # A box's half sizes, or an ellipsoid's radii (a rigid one: top, swing).
    round_object = not hasattr(obj.shape, "half")
    half = np.asarray(obj.shape.radii(0.0) if round_object else obj.shape.half, float)
    # What the object rests on (the floor, or spin's table): Gaussians on it are not the object's.
    floor_z = 2 * next(o for o in world.objects if o.name == "table").shape.half[2] if args.scene_name == "spin" else 0.0

    def pose(t: float) -> tuple[np.ndarray, np.ndarray]:
        """Object to normalised world at `t`: x = R p + b."""
        P = obj.pose(float(t))
        return P[:3, :3], scale * (P[:3, 3] - centre)

    R0, b0 = pose(0.0)
    frames = round(1 / scene.dt) + 1
    knot_r = torch.zeros(frames, 3, requires_grad=True)
    knot_t = torch.zeros(frames, 3, requires_grad=True)
    pivot = torch.from_numpy(b0).float()

    def inside(means: np.ndarray, R, b, grow: float) -> np.ndarray:
        p = (means - b) @ R / scale
        above = (means / scale + centre)[:, 2] > floor_z + 0.01
        within = ((p / half) ** 2).sum(1) <= grow**2 if round_object else (np.abs(p) <= half * grow).all(1)
        return within & (above | (p[:, 2] > -0.9 * half[2]))

    def is_object(means: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(inside(means.detach().double().numpy(), R0, b0, OBJECT_MARGIN))

    def motion_at(t: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation vector and pivot translation of the object from time 0 to `t`."""
        if args.motion == "oracle":
            R, b = pose(t)
            rel = R @ R0.T
            return torch.from_numpy(Rotation.from_matrix(rel).as_rotvec()).float(), torch.from_numpy(b - b0).float()
        f = min(max(t / scene.dt, 0.0), frames - 1 - 1e-6)
        i, a = int(f), f - int(f)
        return (1 - a) * knot_r[i] + a * knot_r[i + 1], (1 - a) * knot_t[i] + a * knot_t[i + 1]

    field_offsets = KinematicsGS.offsets_at

    def offsets_at(self, idx, times, noise=0.0, shared_fine=False):
        offs = field_offsets(self, idx, times, noise, shared_fine)
        rows = torch.nonzero(is_object(self.params.means.index_select(0, idx))).squeeze(1)
        if not len(rows):
            return offs
        mu = self.params.means.index_select(0, idx[rows])
        Rq = quat_to_rotmat(normalize_quats(self.params.quats.index_select(0, idx[rows])))
        out = []
        for o, t in zip(offs, times):
            w, b = motion_at(float(t))
            dx = (mu - pivot) @ so3_exp(w[None])[0].T + pivot + b - mu
            dr = torch.einsum("nji,j->ni", Rq, w)  # the object's rotation in each Gaussian's frame
            out.append(Offsets(o.dx.index_copy(0, rows, dx), o.dr.index_copy(0, rows, dr), o.ds.index_copy(0, rows, torch.zeros_like(dx))))
        return out

    decompose = KinematicsGS.decompose

    def decompose_with_object(self, tau=None, recompute=True, in_place=False, keep_static=False, also_dynamic=None):
        rows = is_object(self.params.means)
        return decompose(self, tau, recompute, in_place, keep_static, rows if also_dynamic is None else also_dynamic | rows)

    init_model = Trainer.init_model

    def init_at_time_zero(self):
        init_model(self)
        with torch.no_grad():  # the object's starting points (5 frames' surface samples) to its pose at 0
            mu = self.model.params.means.detach().double().numpy().copy()
            moved = np.zeros(len(mu), bool)
            for k in np.linspace(0, frames - 1, 5).round():
                R, b = pose(k * scene.dt)
                sel = inside(mu, R, b, 1.03) & ~moved
                mu[sel] = ((mu[sel] - b) @ R) @ R0.T + b0
                moved |= sel
            self.model.params.means.data = torch.from_numpy(mu).float()
        print(f"object Gaussians at the start: {int(moved.sum())} of {len(mu)}")
        if args.motion == "rigid":
            lr_r, lr_t = (float(x) for x in args.lr.split(","))
            self.net_opt.add_param_group({"params": [knot_r], "lr": lr_r, "name": "knot_r"})
            self.net_opt.add_param_group({"params": [knot_t], "lr": lr_t, "name": "knot_t"})

    pick_frames = Trainer.pick_frames

    def pick_in_window(self, k, it=0):
        if not args.window:
            return pick_frames(self, k, it)
        edge = min(1.0, 0.05 + it / (args.window * self.cfg.iterations))
        last = max(1, int(edge / scene.dt))
        with torch.no_grad():
            for knots in (knot_r, knot_t):
                knots[0] = 0  # the canonical pose is the object's at time 0
                for j in range(last + 1, frames):
                    knots[j] = knots[last] + (j - last) * (knots[last] - knots[last - 1])
        inside_window = [i for i, f in enumerate(self.scene.train_frames) if f.time <= edge + 1e-9]
        return random.sample(inside_window, min(k, len(inside_window)))

    loss_for = Trainer.loss_for

    def loss_with_smoothness(self, frame, it):
        loss, out = loss_for(self, frame, it)
        if args.smooth > 0:
            second = lambda x: (x[2:] - 2 * x[1:-1] + x[:-2]).pow(2).sum(-1).mean()
            loss = loss + args.smooth * (second(knot_r) + second(knot_t / scale))
        return loss, out

    KinematicsGS.offsets_at = offsets_at
    KinematicsGS.decompose = decompose_with_object
    Trainer.init_model = init_at_time_zero
    if args.motion == "rigid":
        Trainer.pick_frames = pick_in_window
        Trainer.loss_for = loss_with_smoothness

    settings = dict(args.set)
    cfg = make_config("fast", iterations=args.iterations, eval_every=max(args.iterations // 10, 1), seed=args.seed, **settings)
    info = Trainer(scene, args.run_dir, cfg, progress=False).run()
    run = load_run(args.run_dir)
    m = evaluate_model(run.model, scene)
    h, d = m["heldout"], m["train_view_deblur"]
    print(
        f"{args.motion}: held-out {h['psnr']:.2f} / in mask {h['psnr_dynamic']:.2f}; deblurred {d['psnr']:.2f} / "
        f"{d['psnr_dynamic']:.2f}; velocity error {m['velocity_epe_px']:.2f} px a frame; dynamic {info['dynamic_share']:.0%}"
    )
    if args.motion == "rigid":
        errors = []
        for j in range(frames):
            R, _ = pose(j * scene.dt)
            learned = so3_exp(knot_r[j].detach()[None])[0].double().numpy()
            errors.append(np.degrees(Rotation.from_matrix(learned.T @ R @ R0.T).magnitude()))
        b_true = pose(1.0)[1] - b0
        print("rotation error, degrees, every third frame:", " ".join(f"{e:.0f}" for e in errors[::3]))
        print(f"translation error at the last frame: {np.linalg.norm(knot_t[-1].detach().numpy() - b_true) / scale:.3f} world units")
    rows = []
    for frame in sorted(scene.test_frames, key=lambda f: f.time)[:: max(1, len(scene.test_frames) // 5)][:5]:
        with torch.no_grad():
            img = render_at(run.model, frame, exposure=0.0, dt=scene.dt)[0].image.clamp(0, 1).numpy()
        rows.append(np.concatenate([frame.image(), img], 1))
    picture = np.concatenate(rows, 0)
    Image.fromarray((picture * 255).astype(np.uint8)).save(f"{args.run_dir}/probe.png")


if __name__ == "__main__":
    main()
