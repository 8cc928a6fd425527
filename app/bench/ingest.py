"""Ingest benchmark: `kgs-app bench ingest [CLIP ...]`.

For each clip (by default the shared `walk` and `kitchen` pairs, blurry + sharp camera) the
frames are decoded, and features and matches computed once (the product's frame-set cache, under
`--out/cache`), then every mapper in `--mappers` poses them. Per clip and mapper it prints the
seconds per stage, the frames posed per camera, the mean reprojection error, the points, and two
checks of pose quality:

* **rig consistency** (two-camera clips): the sharp camera is fixed to the blurry one, so the
  pose of camera b relative to camera a should be the same at every time. Reported as the
  median rotation spread (degrees) and the spread of the baseline length (coefficient of
  variation). Lower is better; it needs no ground truth.
* **pose error** (`--synthetic N`: the built-in room scene rendered as an N-frame video, whose
  cameras are known): camera-centre error after a similarity alignment, in % of the scene
  extent, and the error of the rotations relative to the first frame, in degrees.

`--pingpong` also runs each clip played forwards then backwards (twice the frames), for the
time a longer clip takes. Results go to `--out/results.md`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from kgs_core.data.sfm import poses, rig_consistency, rotation_angle_deg

from .machine import machine
from .real import DEFAULT_CLIPS, DEFAULT_DATA, resolve_clip


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(xd.T @ xs / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = (S * np.diag(D)).sum() / (xs**2).sum(1).mean()
    return s, R, mu_d - s * R @ mu_s


def pose_error(P: dict[str, np.ndarray], truth: dict[str, np.ndarray], extent: float) -> tuple[float, float]:
    """(median camera-centre error in % of `extent` after a similarity alignment, median error
    of the rotation relative to the first common frame in degrees)."""
    common = sorted(set(P) & set(truth))
    centre = lambda M: -M[:3, :3].T @ M[:3, 3]
    src = np.stack([centre(P[n]) for n in common])
    dst = np.stack([centre(truth[n]) for n in common])
    s, R, t = umeyama(src, dst)
    err = np.linalg.norm((s * (R @ src.T)).T + t - dst, axis=1) / extent * 100
    r0, q0 = P[common[0]][:3, :3], truth[common[0]][:3, :3]
    rot = [rotation_angle_deg((P[n][:3, :3] @ r0.T).T @ (truth[n][:3, :3] @ q0.T)) for n in common[1:]]
    return float(np.median(err)), float(np.median(rot))


def pingpong_clip(name: str, blur: Path, sharp: Path, root: Path) -> tuple[str, Path, Path]:
    """The clip played forwards then backwards, re-encoded once under `root`."""
    from kgs_core.data.video import decode_video, encode_video

    out = []
    for v in (blur, sharp):
        dst = root / f"{name}_pingpong_{v.stem.rsplit('_', 1)[-1]}.mp4"
        if not dst.is_file():
            frames = decode_video(v, progress=False)
            encode_video(frames + frames[-2:0:-1], dst, fps=6)
        out.append(dst)
    return f"{name} ×2 (ping-pong)", out[0], out[1]


def synthetic_clip(frames: int, size: int, root: Path) -> tuple[str, Path, dict, float]:
    """The room scene as a `frames`-frame video, with its true cameras (by frame name) and the
    extent of its points."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.data.video import encode_video

    folder = root / f"synthetic_room_{frames}x{size}"
    if not folder.is_dir():
        synthesize("room", folder, blur="mild", size=size, frames=frames, progress=True)
    scene = load_scene(folder)
    video = root / f"synthetic_room_{frames}x{size}.mp4"
    if not video.is_file():
        encode_video([(f.image() * 255).round().astype(np.uint8) for f in scene.train_frames], video, fps=12)
    truth = {f"f{i:05d}_a.png": f.camera.viewmat for i, f in enumerate(scene.train_frames)}
    extent = float(np.linalg.norm(scene.points.max(0) - scene.points.min(0)))
    return f"synthetic room ({frames} frames)", video, truth, extent


def bench_clip(
    label: str,
    video: Path,
    eval_video: Path | None,
    size: int,
    mappers: list[str],
    cache: Path,
    truth: dict | None = None,
    extent: float = 1.0,
) -> list[dict]:
    from kgs_core.data.frame_cache import frame_set
    from kgs_core.data.sfm import run_sfm

    rows = []
    with tempfile.TemporaryDirectory(prefix="kgs-bench-ingest-") as tmp:
        t0 = time.perf_counter()
        folder, meta, reused = frame_set(video, eval_video, 1, None, size, cache, True, Path(tmp))
        prep = meta["seconds"]
        if reused:
            print(f"{label}: frame set reused; stage times are those of its first build")
        for mapper in mappers:
            work = Path(tmp) / mapper
            t0 = time.perf_counter()
            result = run_sfm(
                folder / "database.db", folder / "images", work, meta["names_a"], meta["names_b"], meta["sharpness"], mapper, progress=False
            )
            seconds = time.perf_counter() - t0
            row = {
                "clip": label,
                "mapper": mapper,
                "frames": f"{len(meta['names_a'])}+{len(meta['names_b'])}",
                "decode": prep["decode"],
                "features": prep["features"],
                "matching": prep["matching"],
                "mapping": seconds,
                "posed": "failed",
                "reproj": None,
                "points": None,
                "rig": None,
                "pose": None,
            }
            if result is not None:
                P = poses(result.rec)
                na = sum(n in P for n in meta["names_a"])
                nb = sum(n in P for n in meta["names_b"])
                row.update(
                    posed=f"{na}/{len(meta['names_a'])}" + (f" + {nb}/{len(meta['names_b'])}" if meta["names_b"] else ""),
                    reproj=result.rec.compute_mean_reprojection_error(),
                    points=result.rec.num_points3D(),
                    rig=rig_consistency(P),
                    pose=pose_error(P, truth, extent) if truth else None,
                )
            rows.append(row)
            print(format_row(row), flush=True)
            if result is not None and result.attempts and result.attempts[-1].get("stages"):
                print(f"  {mapper} stages (s): {result.attempts[-1]['stages']}", flush=True)
    return rows


HEADER = (
    "| clip | mapper | frames | decode s | features s | matching s | mapping s | total s | posed | "
    "reprojection px | points | rig rotation spread ° | rig baseline cv | centre error % | rotation error ° |\n"
    "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |"
)


def format_row(r: dict) -> str:
    f = lambda v, d=2: "—" if v is None else f"{v:.{d}f}"
    total = r["decode"] + r["features"] + r["matching"] + r["mapping"]
    rig, pose = r["rig"] or (None, None), r["pose"] or (None, None)
    return (
        f"| {r['clip']} | {r['mapper']} | {r['frames']} | {r['decode']:.1f} | {r['features']:.1f} | "
        f"{r['matching']:.1f} | {r['mapping']:.1f} | {total:.1f} | {r['posed']} | {f(r['reproj'])} | "
        f"{r['points'] if r['points'] is not None else '—'} | {f(rig[0])} | {f(rig[1])} | {f(pose[0])} | {f(pose[1])} |"
    )


def main(argv: list[str] | None = None) -> int:
    from kgs_core.data.sfm import MAPPERS

    p = argparse.ArgumentParser(prog="kgs-app bench ingest", description=__doc__.split("\n\n")[0])
    p.add_argument("clips", nargs="*", default=list(DEFAULT_CLIPS), help="clip names in --data, or NAME_blur.EXT paths")
    p.add_argument("--data", default=DEFAULT_DATA)
    p.add_argument("--size", type=int, default=320, help="long side of the frames")
    p.add_argument(
        "--mappers", default="keyframes,global,incremental", help=f"comma-separated, from {', '.join(m for m in MAPPERS if m != 'auto')}"
    )
    p.add_argument("--pingpong", action="store_true", help="also each clip forwards then backwards (twice the frames)")
    p.add_argument(
        "--synthetic", type=int, default=0, metavar="N", help="also the synthetic room as an N-frame video with known cameras (0: no)"
    )
    p.add_argument("--out", default="bench-results/ingest")
    args = p.parse_args(argv)
    mappers = [m.strip() for m in args.mappers.split(",") if m.strip()]
    for m in mappers:
        if m not in MAPPERS or m == "auto":
            p.error(f"--mappers: unknown mapper {m!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = out / "cache"
    rows = []
    for spec in args.clips:
        name, blur, sharp = resolve_clip(spec, Path(args.data))
        rows += bench_clip(name, blur, sharp, args.size, mappers, cache)
        if args.pingpong:
            label, b2, s2 = pingpong_clip(name, blur, sharp, out)
            rows += bench_clip(label, b2, s2, args.size, mappers, cache)
    if args.synthetic:
        label, video, truth, extent = synthetic_clip(args.synthetic, args.size, out)
        rows += bench_clip(label, video, None, args.size, mappers, cache, truth, extent)
    text = (
        f"Machine: {machine()}\n\nCommand: `kgs-app bench ingest {' '.join(argv or [])}`\n\n"
        + HEADER
        + "\n"
        + "\n".join(format_row(r) for r in rows)
        + "\n"
    )
    (out / "results.md").write_text(text)
    print(f"\n{text}\n-> {out / 'results.md'}")
    return 0
