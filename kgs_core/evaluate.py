"""`kgs-app eval RUN`: image metrics against sharp ground truth, inside the dynamic mask too,
decomposition IoU, Gaussian counts and render speed per LoD level."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from .data.formats import load_scene
from .data.scene import Frame, Scene
from .device import computing_on, resolve_device
from .io import atomic_write_text
from .losses import psnr, ssim
from .model.decomposition import decomposition_counts
from .model.dynamic import KinematicsGS
from .model.render import render_model
from .render import rasterize
from .run import LoadedRun, load_run


def lpips_status() -> tuple[object | None, str]:
    """LPIPS needs pretrained backbone weights, which cannot be downloaded here. It is
    computed only if the `lpips` package and its weights are already on this machine."""
    try:
        import lpips  # noqa: F401
    except ImportError:
        return None, "not computed: the lpips package is not installed (its weights cannot be downloaded here)"
    try:
        import lpips

        return lpips.LPIPS(net="alex", verbose=False), "computed with lpips (AlexNet)"
    except Exception as exc:  # missing weights
        return None, f"not computed: LPIPS weights are not available locally ({type(exc).__name__})"


def render_at(
    model: KinematicsGS,
    frame: Frame,
    exposure: float = 0.0,
    dt: float = 1.0,
    background=None,
    colors: torch.Tensor | None = None,
    static: bool = False,
):
    """The rendered image only (its Gaussians' velocities are not computed where not needed);
    image, alpha and depth on the CPU, where the metrics are computed, whatever the model's
    device (on the CPU the same tensors)."""
    out, g = render_model(model, frame.camera, frame.time, exposure, dt, background, colors, static=static, velocity=False)
    return replace(out, image=out.image.cpu(), alpha=out.alpha.cpu(), depth=out.depth.cpu()), g


# One 8-bit level: a render difference below it does not show in a frame the model was trained on.
KR_VISIBLE = 1 / 255
# K.R. counts as acting on a clip when rendering the blur fits the blurry training frames at
# least this much better than rendering sharp: above what rounding moves, under what a scene
# with visible object blur gains (docs/real-footage.md, "What K.R.'s blur does on real footage").
KR_MIN_GAIN_DB = 0.05


@torch.no_grad()
def kr_effect(
    model: KinematicsGS,
    frames: list[Frame],
    exposure: float,
    dt: float,
    count: int = 8,
    camera_motion: Callable[[Frame], tuple] | None = None,
) -> dict:
    """What the kinematic blur (K.R.) does to the training renders: `count` frames spread over
    the clip, each rendered at `exposure` and at 0. `camera_motion(frame)`: the camera's own
    motion at a frame, `(A, b)` as `KinematicsGS.at` takes it, when training models the
    camera's blur too (`--camera-blur`); the blurred render then has it, as training's has.
    `changed_share`: the share of pixels whose two renders differ by more than one 8-bit level
    in some channel; `psnr_blurred` / `psnr_sharp`: each render against the (blurry) training
    frame, and `gain_db` their difference, what modelling the blur buys on the inputs. Rounded
    to 4 decimals, as `run.json` keeps them."""
    picks = [frames[round(i * (len(frames) - 1) / max(count - 1, 1))] for i in range(min(count, len(frames)))]
    changed = pixels = 0
    err_blur = err_sharp = 0.0
    for f in picks:
        gt = torch.from_numpy(f.image())
        sharp = render_at(model, f, 0.0, dt)[0].image.clamp(0, 1)
        motion = None if camera_motion is None else camera_motion(f)
        blurred = render_model(model, f.camera, f.time, exposure, dt, camera_motion=motion, velocity=False)[0].image.clamp(0, 1).cpu()
        diff = (blurred - sharp).abs().amax(-1)
        changed += int((diff > KR_VISIBLE).sum())
        pixels += diff.numel()
        err_blur += float(((blurred - gt) ** 2).mean()) / len(picks)
        err_sharp += float(((sharp - gt) ** 2).mean()) / len(picks)
    to_db = lambda mse: -10 * math.log10(max(mse, 1e-12))  # noqa: E731
    measured = {
        "changed_share": changed / max(pixels, 1),
        "psnr_blurred": to_db(err_blur),
        "psnr_sharp": to_db(err_sharp),
        "gain_db": to_db(err_blur) - to_db(err_sharp),
    }
    return {
        "frames": len(picks),
        "exposure": exposure,
        "camera_blur": camera_motion is not None,
        **{k: round(v, 4) for k, v in measured.items()},
    }


def kr_effect_note(effect: dict) -> str | None:
    """A sentence for the log and `run.json` when K.R.'s measured blur does next to nothing."""
    if effect["gain_db"] >= KR_MIN_GAIN_DB:
        return None
    if effect.get("camera_blur"):
        what = "the blur it models, the motion of the Gaussians and of the camera within the exposure (--camera-blur), hardly shows"
    else:
        what = (
            "the blur it models, each moving Gaussian's own motion within the exposure, hardly shows (a "
            "hand-held camera's blur is mostly its own motion, which --camera-blur models)"
        )
    return (
        f"K.R.'s blur (exposure {effect['exposure']:g}) changes {effect['changed_share']:.2%} of the training "
        f"pixels visibly and moves their PSNR against the blurry frames by {round(effect['gain_db'], 3) or 0.0:+.3f} "
        f"dB, so K.R. does next to nothing on this clip: {what}; --ablate kr trains without it"
    )


def dynamic_mask_render(model: KinematicsGS, frame: Frame, dt: float) -> np.ndarray:
    """Pixels where dynamic Gaussians dominate: render the dynamic flag as a colour."""
    flag = (model.dynamic if model.decomposed else torch.ones(len(model), dtype=torch.bool)).float()[:, None]
    out, _ = render_at(model, frame, 0.0, dt, colors=flag)
    return (out.image[..., 0] > 0.5 * out.alpha[..., 0].clamp_min(1e-6)).numpy() & (out.alpha[..., 0] > 0.5).numpy()


@torch.no_grad()
def velocity_flow(model: KinematicsGS, frame: Frame, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The image motion (pixels per frame interval) that the model's velocities — the ones the
    kinematic covariance is built from — predict at `frame`, seen by a still camera; and the
    rendered alpha. `(H, W, 2)`, `(H, W)`."""
    g = model.at(frame.time, 0.0, dt)
    cam = frame.camera
    R = torch.tensor(cam.viewmat[:3, :3], dtype=torch.float32)
    t = torch.tensor(cam.viewmat[:3, 3], dtype=torch.float32)
    X = g.means @ R.T + t
    V = (g.velocity if g.velocity is not None else torch.zeros_like(g.means)) @ R.T * dt
    z = X[:, 2].clamp_min(1e-6)
    fx, fy = float(cam.K[0, 0]), float(cam.K[1, 1])
    du = fx * (V[:, 0] / z - X[:, 0] * V[:, 2] / z**2)
    dv = fy * (V[:, 1] / z - X[:, 1] * V[:, 2] / z**2)
    viewmat, K = torch.tensor(cam.viewmat, dtype=torch.float32), torch.tensor(cam.K, dtype=torch.float32)
    out = rasterize(g.means, g.opacities, viewmat, K, cam.width, cam.height, covars=g.covars6, colors=torch.stack([du, dv], 1))
    alpha = out.alpha[..., 0]
    return (out.image / alpha.clamp_min(1e-6)[..., None]).numpy(), alpha.numpy()


@torch.no_grad()
def velocity_epe(model: KinematicsGS, scene: Scene) -> float | None:
    """Mean end-point error (pixels per frame interval) between the image motion the model's
    velocities predict and the ground-truth motion, inside the dynamic mask, on the frames of a
    still held-out camera (so the ground truth is object motion alone). None without such
    frames."""
    frames = [f for f in scene.test_frames if f.motion_path and f.mask_path]
    still = len({tuple(np.round(f.camera.viewmat.ravel(), 9)) for f in frames}) == 1
    if not frames or not still:
        return None
    errs = []
    for f in frames:
        mask = f.mask()
        if not mask.any():
            continue
        flow, alpha = velocity_flow(model, f, scene.dt)
        sel = mask & (alpha > 0.5)
        if sel.any():
            errs.append(np.linalg.norm(flow[sel] - f.motion()[sel], axis=-1))
    return float(np.concatenate(errs).mean()) if errs else None


# The dynamic-region mask of a real clip, derived without ground truth (docs/metrics.md): the
# pixels where a static 3DGS of the same clip, rendered at the sharp camera, errs by more than
# STATIC_ERROR_THRESHOLD (mean absolute RGB error), cleaned of thin edges (an opening, then
# connected regions of at least MIN_REGION of the image) and dilated by DILATE of the width.
STATIC_ERROR_THRESHOLD = 0.15
MIN_REGION = 0.002
DILATE = 0.01


def static_error_mask(static_render: np.ndarray, target: np.ndarray) -> np.ndarray:
    """`(H, W)` bool: where a static model's render `(H, W, 3)` misses the target by more than
    the threshold, as regions (a moving object), not the thin misaligned edges that any
    reconstruction of a textured background has."""
    from scipy import ndimage

    err = np.abs(np.clip(static_render, 0, 1) - target).mean(-1)
    mask = ndimage.binary_opening(err > STATIC_ERROR_THRESHOLD, iterations=2)
    labels, n = ndimage.label(mask)
    if n:
        sizes = ndimage.sum(mask, labels, index=np.arange(1, n + 1))
        mask = np.isin(labels, 1 + np.nonzero(sizes >= MIN_REGION * mask.size)[0])
    radius = max(1, round(DILATE * mask.shape[1]))
    return ndimage.binary_dilation(mask, iterations=radius) if mask.any() else mask


def masked_ssim(img: torch.Tensor, gt: torch.Tensor, mask: np.ndarray) -> float | None:
    """SSIM on the bounding box of a non-empty `mask`; None when the box is thinner than the
    11-pixel window."""
    ys, xs = np.nonzero(mask)
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    if min(y1 - y0, x1 - x0) < 11:
        return None
    return float(ssim(img[y0:y1, x0:x1], gt[y0:y1, x0:x1]))


def gradient_energy(img: np.ndarray, mask: np.ndarray) -> float:
    """Mean squared forward difference of the grey image `img (H, W, 3)` over the pixels of
    `mask (H, W)` (both differences, x and y): how much fine detail a region holds. A blur
    lowers it; noise raises it, so it is compared between a render and its ground truth only."""
    grey = np.asarray(img, np.float64).mean(-1)
    gx = np.zeros_like(grey)
    gy = np.zeros_like(grey)
    gx[:, 1:] = grey[:, 1:] - grey[:, :-1]
    gy[1:] = grey[1:] - grey[:-1]
    return float((gx**2 + gy**2)[mask].mean())


def detail_crop(target: np.ndarray, size: int = 160, exclude: np.ndarray | None = None) -> tuple[int, int]:
    """Top-left corner (y, x) of the `size`² window of `target (H, W, 3)` with the most fine
    detail (`gradient_energy`), on a grid of half-windows, skipping windows that overlap
    `exclude (H, W)` by more than a quarter: where a full-size crop shows sharpness (text, edges)."""
    h, w = target.shape[:2]
    size = min(size, h, w)
    everywhere = np.ones((size, size), bool)
    best, corner = -1.0, (0, 0)
    for y in range(0, h - size + 1, max(1, size // 2)):
        for x in range(0, w - size + 1, max(1, size // 2)):
            if exclude is not None and exclude[y : y + size, x : x + size].mean() > 0.25:
                continue
            e = gradient_energy(target[y : y + size, x : x + size], everywhere)
            if e > best:
                best, corner = e, (y, x)
    return corner


class DetailShare:
    """Fine detail of renders and of the blurry inputs as shares of their sharp targets'
    (`gradient_energy` summed over frames), over the whole frame and inside a mask. An input
    of another size than its target (a second camera) counts over the whole frame only, where
    the per-pixel mean compares across sizes."""

    def __init__(self):
        self.sums = np.zeros((2, 4))  # [frame, mask] x [render, its target, input, its target]

    def add(self, render: np.ndarray, blurry_input: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> None:
        everywhere = np.ones(target.shape[:2], bool)
        for row, m in enumerate((everywhere, mask)):
            if m is None or not m.any():
                continue
            sharp = gradient_energy(target, m)
            self.sums[row, :2] += (gradient_energy(render, m), sharp)
            if row == 0:
                self.sums[row, 2:] += (gradient_energy(blurry_input, np.ones(blurry_input.shape[:2], bool)), sharp)
            elif blurry_input.shape == target.shape:
                self.sums[row, 2:] += (gradient_energy(blurry_input, m), sharp)

    def result(self) -> dict:
        """{detail, detail_input, detail_dynamic, detail_input_dynamic}: None where nothing was added."""
        share = lambda row, col: float(self.sums[row, col] / self.sums[row, col + 1]) if self.sums[row, col + 1] > 0 else None  # noqa: E731
        return {"detail": share(0, 0), "detail_input": share(0, 2), "detail_dynamic": share(1, 0), "detail_input_dynamic": share(1, 2)}


def nearest_input(scene: Scene, frame: Frame) -> np.ndarray:
    """The blurry training frame nearest `frame` in time (the input that held-out frame is
    compared with); its own image when `frame` is a training frame."""
    return min(scene.train_frames, key=lambda g: (g is not frame, abs(g.time - frame.time))).image()


def iou(a: np.ndarray, b: np.ndarray) -> float:
    union = (a | b).sum()
    return float("nan") if union == 0 else float((a & b).sum() / union)


def heldout_kind(scene: Scene) -> str:
    """What the held-out PSNR measures: novel views from another camera, or frames of the
    training camera that were left out of training (interpolation in time, not a new viewpoint)."""
    train_cams = {f.camera_id for f in scene.train_frames}
    if all(f.camera_id in train_cams for f in scene.test_frames):
        return "same-camera interpolation (frames of the training video left out of training)"
    return "novel view (a second camera)"


@torch.no_grad()
def evaluate_model(model: KinematicsGS, scene: Scene, lpips_model=None, static: bool = False) -> dict:
    """Metrics over the evaluation views: held-out sharp camera frames, and the training views'
    sharp ground truth (deblurring) when the scene has it. `static`: the run was trained without
    deformation (`--ablate deform`), so render the canonical Gaussians."""
    groups = {}
    if scene.test_frames:
        groups["heldout"] = [(f, f.image()) for f in scene.test_frames]
    train_gt = [f for f in scene.train_frames if f.sharp_path]
    if train_gt:
        groups["train_view_deblur"] = [(f, f.sharp()) for f in train_gt]
    result = {}
    ious = []
    for name, items in groups.items():
        ps, ss, mps, mss, lp = [], [], [], [], []
        detail = DetailShare()
        for f, gt_np in items:
            gt = torch.from_numpy(gt_np)
            # A held-out frame is compared as it was captured: sharp cameras at exposure 0, frames
            # held out of the blurry training video at their own exposure. Deblur targets are sharp.
            exposure = f.exposure if name == "heldout" else 0.0
            out, _ = render_at(model, f, exposure=exposure, dt=scene.dt, static=static)
            img = out.image.clamp(0, 1)
            ps.append(psnr(img, gt))
            ss.append(float(ssim(img, gt)))
            m = f.mask()
            detail.add(img.numpy(), nearest_input(scene, f), gt_np, m)
            if m is not None and m.any():
                mps.append(psnr(img, gt, torch.from_numpy(m)))
                s = masked_ssim(img, gt, m)
                if s is not None:
                    mss.append(s)
                if model.decomposed and not static:
                    ious.append(iou(dynamic_mask_render(model, f, scene.dt), m))
            if lpips_model is not None:
                to = lambda x: x.permute(2, 0, 1)[None] * 2 - 1
                lp.append(float(lpips_model(to(img), to(gt))))
        mean = lambda v: float(np.mean(v)) if v else None
        result[name] = {
            "frames": len(items),
            "psnr": mean(ps),
            "ssim": mean(ss),
            "psnr_dynamic": mean(mps),
            "ssim_dynamic": mean(mss),
            "lpips": mean(lp),
            **detail.result(),
        }
    if scene.test_frames:
        result["heldout"]["kind"] = heldout_kind(scene)
    result["decomposition_iou"] = float(np.nanmean(ious)) if ious and not all(math.isnan(v) for v in ious) else None
    result["velocity_epe_px"] = None if static else velocity_epe(model, scene)
    return result


@torch.no_grad()
def render_fps(model: KinematicsGS, frame: Frame, dt: float, repeats: int = 5) -> float:
    """Renders a second of `frame`'s view, left where it was drawn (on a GPU, waited for: its
    work runs ahead of the clock)."""
    wait = torch.cuda.synchronize if model.params.means.is_cuda else (lambda: None)

    def draw():
        render_model(model, frame.camera, frame.time, 0.0, dt, velocity=False)

    draw()
    wait()
    t0 = time.perf_counter()
    for _ in range(repeats):
        draw()
    wait()
    return repeats / (time.perf_counter() - t0)


def evaluate_run(run_dir: str | Path, scene_dir: str | Path | None = None, device: str = "cpu") -> dict:
    """`kgs-app eval`: the metrics of a run, written to its metrics.json; `device` as `--device`
    (kgs_core/device.py)."""
    dev = resolve_device(device)
    with computing_on(dev):
        return _evaluate_run(load_run(run_dir, dev), run_dir, scene_dir)


def _evaluate_run(run: LoadedRun, run_dir: str | Path, scene_dir: str | Path | None) -> dict:
    scene = load_scene(scene_dir or run.scene_path())
    lp_model, lp_note = lpips_status()
    metrics = evaluate_model(run.model, scene, lp_model, static=run.static_only)
    frame = (scene.test_frames or scene.train_frames)[0]
    metrics["lpips_note"] = lp_note
    metrics["levels"] = []
    for level in range(1, run.n_levels + 1):
        m = run.level(level)
        metrics["levels"].append({"level": level, "gaussians": len(m), "render_fps": render_fps(m, frame, scene.dt)})
    metrics.update(decomposition_counts(run.model, run.static_only))
    metrics["train_seconds"] = run.info.get("train_seconds")
    metrics["scene"] = str(scene.root)
    run_dir = Path(run_dir)
    atomic_write_text(run_dir / "metrics.json", json.dumps(metrics, indent=1))
    atomic_write_text(run_dir / "metrics.md", metrics_markdown(metrics, run.info))
    return metrics


def metrics_markdown(m: dict, info: dict) -> str:
    f = lambda v, d=2: "—" if v is None else f"{v:.{d}f}"
    lines = [
        f"# Evaluation of {info.get('scene_name', '')}",
        "",
        f"Preset/ablations: {info['config'].get('ablate') or 'full method'}; training time {f(m.get('train_seconds'), 1)} s; "
        f"{m['gaussians']:,} Gaussians, {m['dynamic_share']:.1%} dynamic.",
        "",
        "| views | frames | PSNR | SSIM | PSNR (dynamic mask) | SSIM (dynamic mask) | detail (input) | detail in mask (input) | LPIPS |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name in ("heldout", "train_view_deblur"):
        if name in m:
            r = m[name]
            lines.append(
                f"| {name} | {r['frames']} | {f(r['psnr'])} | {f(r['ssim'], 3)} | {f(r['psnr_dynamic'])} | "
                f"{f(r['ssim_dynamic'], 3)} | {f(r.get('detail'))} ({f(r.get('detail_input'))}) | "
                f"{f(r.get('detail_dynamic'))} ({f(r.get('detail_input_dynamic'))}) | {f(r['lpips'], 3)} |"
            )
    lines += [
        "",
        "Detail: the render's fine detail as a share of the sharp target's (1: as sharp; "
        "`evaluate.gradient_energy`), beside the blurry input's share; read it with PSNR, since noise raises it.",
    ]
    if m.get("heldout", {}).get("kind"):
        lines += ["", f"Held-out views: {m['heldout']['kind']}."]
    if info.get("kr_note"):
        lines += ["", f"Kinematic refinement: {info['kr_note']}."]
    if info.get("decomposition_note"):
        lines += ["", f"Static/dynamic decomposition: {info['decomposition_note']}."]
    lines += [
        "",
        f"LPIPS: {m['lpips_note']}.",
        f"Decomposition IoU against the ground-truth dynamic masks: {f(m['decomposition_iou'], 3)}",
        f"Velocity end-point error against ground-truth motion (still held-out camera, dynamic mask): "
        f"{f(m.get('velocity_epe_px'), 3)} px per frame interval",
        "",
        "| LoD level | Gaussians | render FPS (CPU) |",
        "|---|---|---|",
    ]
    for lv in m["levels"]:
        lines.append(f"| {lv['level']} | {lv['gaussians']:,} | {lv['render_fps']:.1f} |")
    return "\n".join(lines) + "\n"
