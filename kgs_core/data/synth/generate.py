"""Renders a named synthetic scene to a dataset folder (Nerfies + D-NeRF layouts) with ground
truth: sharp mid-exposure frames, dynamic masks and per-pixel image motion, from the blurry
training camera and from a sharp held-out camera (the BARD-GS protocol).

Every image integrates over its pixels' area, as a camera's sensor does: a sharp frame averages a
grid of rays across each pixel, a blurry frame gives each instant of its exposure its own point in
the pixel. One ray through the centre would alias the textures' edges into false detail, which a
reconstruction is then scored against (docs/data.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...io import atomic_directory
from ...job_options import BLURS  # noqa: E402
from ...threads import parallel_map
from ..formats import write_dnerf, write_nerfies
from ..images import write_image, write_mask, write_motion
from ..scene import Camera, Frame, Scene
from .raytrace import World
from .scenes import SCENES, build_world, heldout_camera, intrinsics, shaky_training_camera

BLUR_LEVELS = dict(zip(BLURS, (0.0, 0.5, 1.0)))  # exposure, in frame intervals
DEFAULT_SCENE = "sheet"
SYNTH_FPS = 30.0  # the synthetic camera's frame rate: what a frame's time reads as in seconds


@dataclass
class Rendered:
    color: np.ndarray  # (H, W, 3)
    obj: np.ndarray  # (H, W) hit object index, -1 = nothing
    local: np.ndarray  # (H, W, 3)
    depth: np.ndarray  # (H, W)


def camera_rays(
    viewmat: np.ndarray, K: np.ndarray, width: int, height: int, offset: tuple[float, float] = (0.0, 0.0)
) -> tuple[np.ndarray, np.ndarray]:
    """Origins and directions (unnormalised, camera z = 1, so the ray parameter is depth) through
    each pixel's centre moved by `offset` (x, y) pixels."""
    j, i = np.meshgrid(np.arange(width) + 0.5 + offset[0], np.arange(height) + 0.5 + offset[1])
    d_cam = np.stack([(j - K[0, 2]) / K[0, 0], (i - K[1, 2]) / K[1, 1], np.ones_like(j)], -1).reshape(-1, 3)
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    d_world = d_cam @ R  # R^T d
    origin = -R.T @ t
    return np.broadcast_to(origin, d_world.shape), d_world


def render(
    world: World, viewmat: np.ndarray, K: np.ndarray, width: int, height: int, t: float, offset: tuple[float, float] = (0.0, 0.0)
) -> Rendered:
    """One ray a pixel, through its centre moved by `offset` pixels."""
    o, d = camera_rays(viewmat, K, width, height, offset)
    res = world.trace(o, d, t)
    return Rendered(
        res.color.reshape(height, width, 3),
        res.obj.reshape(height, width),
        res.local.reshape(height, width, 3),
        res.depth.reshape(height, width),
    )


def grid_offsets(n: int) -> list[tuple[float, float]]:
    """The centres of an `n x n` grid over a pixel, as offsets from its centre; odd `n` includes
    the centre itself."""
    c = (np.arange(n) + 0.5) / n - 0.5
    return [(float(x), float(y)) for y in c for x in c]


def halton_offsets(n: int) -> list[tuple[float, float]]:
    """`n` well-spread points in a pixel (the Halton sequence in bases 2 and 3), as offsets from
    its centre: one per instant of a blurry frame's exposure, so that the frame integrates over
    the pixel's area as well as over time."""

    def radical_inverse(i: int, base: int) -> float:
        f, r = 1.0, 0.0
        while i:
            f /= base
            r += f * (i % base)
            i //= base
        return r

    return [(radical_inverse(i, 2) - 0.5, radical_inverse(i, 3) - 0.5) for i in range(1, n + 1)]


def project(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> np.ndarray:
    p = points @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = p @ K.T
    return uv[:, :2] / uv[:, 2:3]


def image_motion(world: World, r: Rendered, cam_at, K: np.ndarray, t: float, dt: float) -> np.ndarray:
    """Per-pixel motion of the visible surface point, in pixels per frame interval, including
    camera motion (central difference over +-5% of a frame)."""
    h = 0.05 * dt
    motion = np.zeros(r.obj.shape + (2,), np.float32)
    for k, ob in enumerate(world.objects):
        sel = r.obj == k
        if not sel.any():
            continue
        local = r.local[sel]
        p_plus = project(ob.world_point(local, t + h), cam_at(t + h), K)
        p_minus = project(ob.world_point(local, t - h), cam_at(t - h), K)
        motion[sel] = ((p_plus - p_minus) / (2 * h) * dt).astype(np.float32)
    return motion


def synthesize(
    name: str = DEFAULT_SCENE,
    out: str | Path = "scene",
    blur: str = "mild",
    seed: int = 0,
    size: int = 128,
    frames: int = 60,
    subframes: int = 16,
    pixel_grid: int = 3,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Writes the dataset folder `out` and returns its path (written to a temporary sibling and
    renamed when complete). A sharp frame averages `pixel_grid`² rays a pixel (odd: its centre
    ray gives the masks and motion); a blurry one `max(subframes, pixel_grid²)` instants of its
    exposure, each through its own point in the pixel. Frames render on every core."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    if blur not in BLUR_LEVELS:
        raise ValueError(f"blur must be one of {', '.join(BLUR_LEVELS)}, got {blur!r}")
    if frames < 2 or size < 16 or subframes < 1:
        raise ValueError("need frames >= 2, size >= 16 and subframes >= 1")
    if pixel_grid < 1 or pixel_grid % 2 == 0:
        raise ValueError(f"pixel_grid must be odd and at least 1 (its centre ray gives the masks), got {pixel_grid}")
    exposure = BLUR_LEVELS[blur]
    world = build_world(name, seed)
    dynamic = {k for k, ob in enumerate(world.objects) if ob.dynamic}
    K = intrinsics(size, size)
    rigs = {0: shaky_training_camera(seed), 1: heldout_camera()}
    dt = 1.0 / (frames - 1)
    n_sub = max(subframes, pixel_grid**2) if exposure > 0 else 1
    sharp_offsets, blur_offsets = grid_offsets(pixel_grid), halton_offsets(n_sub)
    times = (np.arange(n_sub) + 0.5) / n_sub - 0.5  # midpoints of equal slices of the exposure
    out = Path(out)
    point_frames = set(np.linspace(0, frames - 1, 5).round().astype(int).tolist())

    def exposure_mean(cam_at, t: float, exposure_len: float) -> np.ndarray:
        instants = t + times * exposure_len
        return np.mean([render(world, cam_at(u), K, size, size, u, p).color for u, p in zip(instants, blur_offsets)], axis=0)

    def render_frame(i: int, tmp: Path) -> list[tuple[Frame, tuple | None]]:
        """Writes frame `i` of both cameras; returns their Frames and the training camera's
        surface points where `i` is one of the point frames."""
        t = i * dt
        done = []
        for cam_id, cam_at in rigs.items():
            fid = f"c{cam_id}_{i:05d}"
            paths = {
                kind: tmp / kind / "1x" / f"{fid}{ext}"
                for kind, ext in (("rgb", ".png"), ("sharp", ".png"), ("mask", ".png"), ("motion", ".npy"))
            }
            grid = [render(world, cam_at(t), K, size, size, t, p) for p in sharp_offsets]
            centre = grid[len(grid) // 2]
            sharp = np.mean([g.color for g in grid], axis=0)
            frame_exposure = exposure if cam_id == 0 else 0.0
            blurry = exposure_mean(cam_at, t, dt * frame_exposure) if frame_exposure > 0 else sharp
            write_image(paths["rgb"], blurry)
            write_image(paths["sharp"], sharp)
            write_mask(paths["mask"], np.isin(centre.obj, list(dynamic)))
            write_motion(paths["motion"], image_motion(world, centre, cam_at, K, t, dt))
            frame = Frame(
                id=fid,
                image_path=paths["rgb"],
                time=t,
                camera=Camera(K=K.copy(), viewmat=cam_at(t), width=size, height=size),
                exposure=frame_exposure,
                split="train" if cam_id == 0 else "test",
                camera_id=cam_id,
                sharp_path=paths["sharp"],
                mask_path=paths["mask"],
                motion_path=paths["motion"],
            )
            centre.color = sharp  # the stand-in SfM points take the frame's colours, not the one ray's
            points = None
            if cam_id == 0 and i in point_frames:
                points = surface_points(world, centre, cam_at(t), K, t, dynamic, keep_dynamic=True)
            done.append((frame, points))
        return done

    with atomic_directory(out, overwrite=overwrite) as tmp:
        scene_frames, point_sets, color_sets = [], [], []
        # A thread per core: numpy releases the GIL in the ray tracer's array work.
        for done in parallel_map(lambda i: render_frame(i, tmp), list(range(frames)), desc=f"synth {name}", progress=progress):
            for frame, points in done:
                scene_frames.append(frame)
                if points is not None:
                    point_sets.append(points[0])
                    color_sets.append(points[1])
        scene_frames.sort(key=lambda f: (f.camera_id, f.time))
        scene = Scene(
            name=out.name,
            root=tmp,
            frames=scene_frames,
            points=np.concatenate(point_sets),
            point_colors=np.concatenate(color_sets),
            source_format="synthetic",
            extras={
                "fps": SYNTH_FPS,
                "generator": {
                    "scene": name,
                    "blur": blur,
                    "exposure": exposure,
                    "seed": seed,
                    "size": size,
                    "frames": frames,
                    "subframes": n_sub,
                    "dynamic_objects": [world.objects[k].name for k in sorted(dynamic)],
                    "points": "surface samples of the visible geometry in 5 frames (stands in for SfM)",
                },
            },
        )
        scene.normalize()
        scene.extras["normalized"] = True
        scene.extras["normalization"] = scene.normalization.to_dict()
        write_nerfies(scene, tmp)
        write_dnerf(scene, tmp)
    return out


def surface_points(world: World, r: Rendered, viewmat, K, t, dynamic: set[int], keep_dynamic: bool, stride: int = 3):
    """World points and colours of every `stride`-th pixel's surface (dynamic ones only when
    `keep_dynamic`): the generator's stand-in for SfM points. Taken from 5 frames, the moving
    objects leave points along their path, as SfM's scattered dynamic points do."""
    obj = r.obj[::stride, ::stride].reshape(-1)
    depth = r.depth[::stride, ::stride].reshape(-1)
    color = r.color[::stride, ::stride].reshape(-1, 3)
    h, w = r.obj.shape
    o, d = camera_rays(viewmat, K, w, h)
    d = d.reshape(h, w, 3)[::stride, ::stride].reshape(-1, 3)
    o = o.reshape(h, w, 3)[::stride, ::stride].reshape(-1, 3)
    keep = (obj >= 0) & np.isfinite(depth)
    if not keep_dynamic:
        keep &= ~np.isin(obj, list(dynamic))
    return o[keep] + depth[keep, None] * d[keep], color[keep]
