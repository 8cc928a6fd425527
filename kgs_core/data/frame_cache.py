"""The ingest's caches: decoded frame sets (frames, their sharpness, features and matches), and
the newest posed model of each frame set, whatever the size it was mapped at.

A frame set is named by its videos (path, size, modification time) and how they were sampled
(`frame_set_key`); it is built atomically, so an interrupted ingest leaves nothing half-written.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
from PIL import Image

from ..io import atomic_directory
from ..threads import parallel_map
from .scene import SceneError
from .sfm import extract_and_match
from .video import decode_video

PNG_LEVEL = 1  # zlib level for frames: level 6 (PIL's default) took 4x as long for files ~1.3x smaller


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: low for blurry frames."""
    g = img.astype(np.float32).mean(axis=-1)
    lap = g[1:-1, 2:] + g[1:-1, :-2] + g[2:, 1:-1] + g[:-2, 1:-1] - 4 * g[1:-1, 1:-1]
    return float(lap.var())


def default_cache_dir() -> Path:
    return Path(os.environ.get("KGS_CACHE_DIR") or Path.home() / ".cache" / "kinematics-gs") / "ingest"


def frame_set_key(videos: list[Path], every: int, max_frames: int | None, max_size: int | None) -> str:
    """Names one decoded frame set: the videos (path, size, modification time) and how they were
    sampled. Features and matches depend on nothing else."""
    parts = []
    for v in videos:
        st = v.stat()
        parts.append(f"{v.resolve()}:{st.st_size}:{st.st_mtime_ns}")
    parts.append(f"every={every}:max_frames={max_frames}:max_size={max_size}:v1")
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:20]


def decode_frames(
    folder: Path, video: Path, eval_video: Path | None, every: int, max_frames: int | None, max_size: int | None, progress: bool
) -> dict:
    """Decodes both videos into `folder/images` and scores each frame's sharpness:
    `{"names_a", "names_b", "sharpness", "seconds": {"decode"}}`."""
    t0 = time.perf_counter()
    frames_a = decode_video(video, every, max_frames, max_size, progress)
    frames_b: list[np.ndarray] = []
    if eval_video is not None:
        frames_b = decode_video(eval_video, every, max_frames, max_size, progress)
        if len(frames_b) != len(frames_a):
            raise SceneError(
                f"frame counts differ: {video} has {len(frames_a)}, {eval_video} has {len(frames_b)} "
                "(synchronised videos must have one frame per time step)"
            )
    (folder / "images").mkdir(parents=True)
    names_a = [f"f{i:05d}_a.png" for i in range(len(frames_a))]
    names_b = [f"f{i:05d}_b.png" for i in range(len(frames_b))]

    def save(job: tuple[str, np.ndarray]) -> float:
        name, img = job
        Image.fromarray(img).save(folder / "images" / name, compress_level=PNG_LEVEL)
        return round(sharpness(img), 2)

    jobs = list(zip(names_a, frames_a)) + list(zip(names_b, frames_b))
    scores = dict(zip([name for name, _ in jobs], parallel_map(save, jobs)))
    return {"names_a": names_a, "names_b": names_b, "sharpness": scores, "seconds": {"decode": round(time.perf_counter() - t0, 2)}}


def build_frame_set(
    folder: Path, video: Path, eval_video: Path | None, every: int, max_frames: int | None, max_size: int | None, progress: bool
) -> dict:
    """`decode_frames`, then features extracted and matched into `folder/database.db`; writes
    `folder/frames.json` (names, sharpness, timings)."""
    meta = decode_frames(folder, video, eval_video, every, max_frames, max_size, progress)
    timings = extract_and_match(folder / "database.db", folder / "images", meta["names_a"], meta["names_b"], progress)
    meta["seconds"].update({k: round(v, 2) for k, v in timings.items()})
    (folder / "frames.json").write_text(json.dumps(meta))
    return meta


def frame_set(
    video: Path,
    eval_video: Path | None,
    every: int,
    max_frames: int | None,
    max_size: int | None,
    cache_dir: Path | None,
    progress: bool,
    scratch: Path,
) -> tuple[Path, dict, bool]:
    """(folder, metadata, reused): the cached frame set when there is one, else a new one, built
    atomically into the cache (or into `scratch` when caching is off)."""
    if cache_dir is None:
        folder = scratch / "frames"
        return folder, build_frame_set(folder, video, eval_video, every, max_frames, max_size, progress), False
    videos = [video] + ([eval_video] if eval_video else [])
    folder = Path(cache_dir) / frame_set_key(videos, every, max_frames, max_size)
    meta_path = folder / "frames.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            if progress:
                print(f"reusing decoded frames, features and matches from {folder}", flush=True)
            return folder, meta, True
        except (OSError, ValueError):
            pass  # unreadable: rebuild it
    with atomic_directory(folder, overwrite=True) as tmp:
        meta = build_frame_set(tmp, video, eval_video, every, max_frames, max_size, progress)
    return folder, meta, False


def pose_cache_dir(cache_dir: Path, videos: list[Path], every: int, max_frames: int | None) -> Path:
    """Where the newest posed model of a frame set is kept, whatever the size it was mapped at."""
    return Path(cache_dir) / "poses" / frame_set_key(videos, every, max_frames, None)


def save_poses(folder: Path, rec, max_size: int | None, mapper: str, attempts: list, lens: str, lens_report: dict) -> None:
    """Keeps a posed model for re-runs at another size (`load_poses`), atomically; `lens` is the
    `--lens` it was made with, `lens_report` what its refit did."""
    with atomic_directory(folder, overwrite=True) as tmp:
        (tmp / "sparse").mkdir()
        rec.write(str(tmp / "sparse"))
        (tmp / "poses.json").write_text(
            json.dumps({"max_size": max_size, "mapper": mapper, "attempts": attempts, "lens": lens, "lens_report": lens_report})
        )


def load_poses(folder: Path):
    """`(pycolmap.Reconstruction, its metadata)` kept by `save_poses`; None when there is none or
    it cannot be read (the caller then maps anew)."""
    import pycolmap

    try:
        meta = json.loads((folder / "poses.json").read_text())
        rec = pycolmap.Reconstruction(str(folder / "sparse"))
    except (OSError, ValueError, RuntimeError):
        return None
    return (rec, meta) if isinstance(meta, dict) and rec.num_images() else None


def rescale_reconstruction(rec, sizes: dict[str, tuple[int, int]]) -> None:
    """Rescales each camera of `rec` and its images' keypoints to the size its video's frames
    now have (`sizes`: the name tag "a" or "b" -> (width, height)), so the model describes frames
    decoded at another `--max-size`. Poses and points are unchanged: only pixels change units."""
    factors = {}
    for im in rec.images.values():
        if im.camera_id not in factors:
            cam = rec.cameras[im.camera_id]
            w, h = sizes[im.name[-5]]  # "f00012_a.png" -> "a"
            factors[im.camera_id] = np.array([w / cam.width, h / cam.height])
            cam.rescale(w, h)
        for p in im.points2D:
            p.xy = p.xy * factors[im.camera_id]
    rec.update_point_3d_errors()  # (COLMAP keeps each point's error: recompute it in the new pixels)


def posed_before(
    poses_dir: Path,
    video: Path,
    eval_video: Path | None,
    every: int,
    max_frames: int | None,
    max_size: int | None,
    lens: str,
    progress: bool,
    scratch: Path,
):
    """The frame set's model mapped before (at any `--max-size`, with the same `--lens`), rescaled
    to frames decoded now at `max_size`: `(reconstruction, images folder, decode metadata,
    {"mapper", "attempts", "from", "lens_report"})`, or None when there is none or its frames are not
    these (then SfM runs)."""
    kept = load_poses(poses_dir)
    if kept is None:
        return None
    rec, mapped = kept
    if mapped.get("lens", "simple") != lens:  # (models kept before the lens refit have none)
        return None
    folder = scratch / "frames"
    meta = decode_frames(folder, video, eval_video, every, max_frames, max_size, progress)
    if not {im.name for im in rec.images.values()} <= set(meta["names_a"] + meta["names_b"]):
        shutil.rmtree(folder)
        return None
    sizes = {}
    for tag, names in (("a", meta["names_a"]), ("b", meta["names_b"])):
        if names:
            with Image.open(folder / "images" / names[0]) as im:
                sizes[tag] = im.size
    rescale_reconstruction(rec, sizes)
    size = mapped.get("max_size")
    mapper = mapped.get("mapper", "?")
    source = f"{mapper} model mapped at {f'{size} px' if size else 'full size'}, rescaled"
    if progress:
        print(f"reusing the poses of the {source} (--mapper NAME or --no-cache maps anew)", flush=True)
    return (
        rec,
        folder / "images",
        meta,
        {"mapper": mapper, "attempts": mapped.get("attempts", []), "from": source, "lens_report": mapped.get("lens_report", {})},
    )
