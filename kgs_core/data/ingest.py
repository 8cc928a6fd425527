"""Video ingest: decode, subsample, score sharpness, structure from motion (`sfm.py`), and write a
Nerfies-layout scene.

Two shapes of input:
- one video (the common case): every `holdout_every`-th frame is held out of training and scored
  as a test view. Those are same-camera interpolations at the training exposure, not novel
  views, and the scene records so (`ingest.holdout` in kgs.json).
- two synchronised videos (the BARD-GS protocol: a sharp camera beside the blurry one): the
  second one is registered into the same model and becomes the held-out test views.

The decoded frames, their sharpness, features and matches are cached per frame set (videos,
stride, frame cap and size) under `cache_dir`, so a re-run with another mapper starts at mapping;
the newest posed model of the frames is kept whatever the size (`cache_dir/poses`), so a re-run
at another `max_size` with the `auto` mapper only decodes the frames and rescales the cameras.
A still camera can skip SfM altogether (`fixed_camera`): every frame gets one pose.
"""

from __future__ import annotations

import math
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from ..io import atomic_directory
from ..progress import announce
from ..threads import parallel_map
from .formats import write_nerfies
from .formats.colmap import camera_from_colmap
from .frame_cache import PNG_LEVEL, default_cache_dir, frame_set, pose_cache_dir, posed_before, save_poses
from .lens import LENSES, refine_lens
from .scene import Camera, Frame, Scene, SceneError
from .sfm import MAPPERS, run_sfm
from .video import count_frames, decode_video, frame_rate

AUTO_MAX_FRAMES = 300  # frames kept from a long video when no stride is given
# Seconds per frame at 320 px on two cores by stage, measured end to end (docs/results.md,
# "Ingest"); only for the estimate printed at the start.
SECONDS_PER_FRAME_320 = {"decode": 0.018, "features": 0.024, "matching": 0.017, "mapping": 0.045}
FIXED_CAMERA_FOV_DEG = 60.0  # assumed horizontal field of view when no SfM runs


@dataclass
class IngestReport:
    video: str
    eval_video: str | None
    frames: int
    eval_frames: int
    registered: int
    eval_registered: int
    mean_reprojection_error_px: float
    points: int
    seconds: dict = field(default_factory=dict)
    mapper: str = ""
    attempts: list = field(default_factory=list)
    stride: int = 1
    # Set when the poses came from an earlier ingest of the same frames at another size.
    poses_from: str | None = None
    stride_reason: str = ""
    holdout: str = ""
    cached: bool = False
    # The lens refit after mapping (`lens.refine_lens`): kept or not, the reprojection error before
    # and after; empty when none was tried (`--lens simple`, a fixed camera).
    lens: dict = field(default_factory=dict)
    # Frames a second of the frames kept (the video's rate over the stride); None when unknown.
    fps: float | None = None

    @property
    def registered_fraction(self) -> float:
        return self.registered / max(self.frames, 1)


def choose_stride(video: Path, every: int | None, max_frames: int | None, auto_max_frames: int = AUTO_MAX_FRAMES) -> tuple[int, str]:
    """(stride, why). A given `every` wins; else a long video is thinned to about
    `auto_max_frames` frames (spread over the whole clip, unlike a frame cap, which keeps the
    start)."""
    if every is not None:
        if every < 1:
            raise SceneError(f"--every must be at least 1, got {every}")
        return every, "given"
    total = count_frames(video)
    stride = max(1, round(total / auto_max_frames))  # 301-449 frames stay whole: halving them loses more
    if max_frames or stride == 1:
        return 1, f"all {total} frames"
    return stride, (
        f"{video.name} has {total} frames: kept every {ordinal(stride)} ({math.ceil(total / stride)} "
        f"frames) to stay near {auto_max_frames}; pass --every to choose"
    )


def ordinal(n: int) -> str:
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def estimate_seconds(frames: int, long_side: int | None, cached: bool) -> float:
    """A rough ingest time: the measured per-frame rates, scaled by pixels for the image stages."""
    scale = ((long_side or 960) / 320) ** 2
    rates = SECONDS_PER_FRAME_320
    prep = 0.0 if cached else frames * (rates["decode"] * scale + rates["features"] * scale + rates["matching"])
    return prep + frames * rates["mapping"]


def undistort_frame(cam, image_path: Path):
    """(pinhole pycolmap camera, undistorted RGB uint8 array) for one distorted frame."""
    import pycolmap

    bitmap = pycolmap.Bitmap.from_array(np.asarray(Image.open(image_path).convert("RGB")))
    pixels, pinhole = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, cam)
    return pinhole, np.ascontiguousarray(pixels.to_array()[..., :3])


def frame_ranges(indices: list[int]) -> str:
    """`[3, 4, 5, 9]` -> `"3-5, 9"`."""
    out, start = [], None
    for k, i in enumerate(indices):
        if start is None:
            start = i
        if k + 1 == len(indices) or indices[k + 1] != i + 1:
            out.append(f"{start}" if start == i else f"{start}-{i}")
            start = None
    return ", ".join(out)


from ..job_options import DEFAULT_MAX_SIZE  # noqa: E402  (the job's options, declared once)


def ingest(
    video: str | Path,
    out: str | Path,
    eval_video: str | Path | None = None,
    every: int | None = None,
    max_frames: int | None = None,
    max_size: int | None = DEFAULT_MAX_SIZE,
    exposure: float = 0.5,
    mapper: str = "auto",
    holdout_every: int | None = None,
    fixed_camera: bool = False,
    cache_dir: str | Path | None | bool = True,
    min_registered: float = 0.3,
    overwrite: bool = False,
    undistort: bool = True,
    lens: str = "opencv",
    progress: bool = True,
) -> IngestReport:
    """Builds a scene folder from a video. `exposure` is the assumed shutter fraction of the
    training video (unknown from the file; 0.5 is typical for indoor hand-held footage).

    `every`: keep every k-th frame (None: all frames, or about AUTO_MAX_FRAMES of a long video).
    `holdout_every`: with one video, every n-th frame is a test view (None: 8; 0: none).
    `cache_dir`: where frame sets are cached (True: `default_cache_dir()`; None or False: off).
    With `undistort` (the default) every frame whose SfM camera has lens distortion is
    resampled to a pinhole camera by pycolmap's undistorter (cropped to valid pixels), since the
    rasteriser is pinhole; the distorted model stays under `colmap/sparse/0`.
    `lens`: "opencv" refits each camera as COLMAP's OPENCV lens after mapping, kept where it
    lowers the reprojection error (`lens.refine_lens`); "simple" keeps the mappers' SIMPLE_RADIAL."""
    video = Path(video)
    eval_video = Path(eval_video) if eval_video is not None else None
    if not 0 <= exposure <= 1:
        raise SceneError(f"exposure must be in [0, 1], got {exposure}")
    if mapper not in MAPPERS:
        raise SceneError(f"mapper must be one of {', '.join(MAPPERS)}, got {mapper!r}")
    if lens not in LENSES:
        raise SceneError(f"lens must be one of {', '.join(LENSES)}, got {lens!r}")
    for v in [video] + ([eval_video] if eval_video else []):
        if not v.is_file():
            raise SceneError(f"video not found: {v}")
    if holdout_every is None:
        holdout_every = 0 if eval_video is not None else 8
    if holdout_every < 0 or holdout_every == 1:
        raise SceneError(f"holdout_every must be 0 (none) or at least 2, got {holdout_every}")
    stride, stride_reason = choose_stride(video, every, max_frames)
    if progress and every is None and stride > 1:
        print(stride_reason, flush=True)
    cache = default_cache_dir() if cache_dir is True else (Path(cache_dir) if cache_dir else None)
    if fixed_camera:
        return _ingest_fixed_camera(
            video, Path(out), eval_video, stride, stride_reason, max_frames, max_size, exposure, holdout_every, overwrite, progress
        )
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="kgs-sfm-") as tmpdir:
        work = Path(tmpdir)
        if progress:
            count = count_frames(video)
            kept = min(math.ceil(count / stride), max_frames or count) * (2 if eval_video else 1)
            print(
                f"ingesting {kept} frames; expect about {estimate_seconds(kept, max_size, False):.0f} s "
                "(less when the frames were ingested before)",
                flush=True,
            )
        videos = [video] + ([eval_video] if eval_video else [])
        kept = None
        if cache is not None and mapper == "auto":
            kept = posed_before(
                pose_cache_dir(cache, videos, stride, max_frames), video, eval_video, stride, max_frames, max_size, lens, progress, work
            )
        if kept is not None:
            rec, images, meta, mapped = kept
            names_a, names_b, scores = meta["names_a"], meta["names_b"], meta["sharpness"]
            timings, reused = dict(meta["seconds"]), True
            mapper_used, attempts, lens_report = mapped["mapper"], mapped["attempts"], mapped["lens_report"]
        else:
            folder, meta, reused = frame_set(video, eval_video, stride, max_frames, max_size, cache, progress, work)
            images = folder / "images"
            names_a, names_b, scores = meta["names_a"], meta["names_b"], meta["sharpness"]
            timings = {} if reused else dict(meta["seconds"])
            t0 = time.perf_counter()
            result = run_sfm(
                folder / "database.db", images, work, names_a, names_b, scores, mapper, progress=progress, probe_lens=lens == "opencv"
            )
            timings["mapping"] = time.perf_counter() - t0
            if result is None:
                raise SceneError(
                    f"structure from motion found no model in {video} ({len(names_a)} frames): too "
                    "little texture or parallax? Try another stride (--every), a longer clip, or "
                    "--fixed-camera for a camera that does not move"
                )
            rec, mapper_used, attempts = result.rec, result.mapper, result.attempts
            lens_report = {}
            if lens == "opencv":
                t0 = time.perf_counter()
                announce("lens")
                rec, lens_report = refine_lens(rec, probe=result.lens_probe)
                timings["lens"] = time.perf_counter() - t0
        n = len(names_a)
        reg = {im.name: im for im in rec.images.values() if im.has_pose}
        n_a = sum(1 for nm in names_a if nm in reg)
        n_b = sum(1 for nm in names_b if nm in reg)
        if n_a < max(2, min_registered * n):
            missing = [i for i, nm in enumerate(names_a) if nm not in reg]
            raise SceneError(
                f"structure from motion posed only {n_a} of {n} frames of {video} (need {min_registered:.0%}; "
                f"mappers tried: {', '.join(a['mapper'] + ' ' + a['outcome'] for a in attempts)}). "
                f"Frames not posed (index after the stride of {stride}): {frame_ranges(missing)}. Try another "
                "stride (--every), a longer clip with more camera movement, or --fixed-camera for a camera that "
                "does not move"
            )
        error_px = float(rec.compute_mean_reprojection_error())
        if cache is not None and kept is None:
            save_poses(pose_cache_dir(cache, videos, stride, max_frames), rec, max_size, mapper_used, attempts, lens, lens_report)
        report = IngestReport(
            video=str(video),
            eval_video=str(eval_video) if eval_video else None,
            frames=n,
            eval_frames=len(names_b),
            registered=n_a,
            eval_registered=n_b,
            mean_reprojection_error_px=error_px,
            points=rec.num_points3D(),
            mapper=mapper_used,
            attempts=attempts,
            stride=stride,
            stride_reason=stride_reason,
            cached=reused,
            poses_from=None if kept is None else kept[3]["from"],
            lens=lens_report,
            fps=_kept_rate(video, stride),
            holdout=(
                "second camera (novel view)"
                if eval_video
                else f"same-camera interpolation: every {ordinal(holdout_every)} frame"
                if holdout_every
                else "none"
            ),
        )
        t0 = time.perf_counter()
        out = Path(out)
        with atomic_directory(out, overwrite=overwrite) as tmp:
            (tmp / "rgb" / "1x").mkdir(parents=True)

            def write_frame(nm: str, cam_id: int) -> Frame:
                im = reg[nm]
                i = int(nm[1:6])
                cam = rec.cameras[im.camera_id]
                K, dist = camera_from_colmap(cam, f"{video}: SfM camera")
                width, height = int(cam.width), int(cam.height)
                fid = f"c{cam_id}_{i:05d}"
                dst = tmp / "rgb" / "1x" / f"{fid}.png"
                if undistort and np.any(dist != 0):
                    cam, pixels = undistort_frame(cam, images / nm)
                    K, dist = camera_from_colmap(cam, f"{video}: undistorted camera")
                    width, height = int(cam.width), int(cam.height)
                    Image.fromarray(pixels).save(dst, compress_level=PNG_LEVEL)
                else:
                    shutil.copyfile(images / nm, dst)
                viewmat = np.eye(4)
                cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
                viewmat[:3] = np.asarray(cfw.matrix())
                held = cam_id == 1 or (holdout_every and i % holdout_every == holdout_every // 2)
                return Frame(
                    id=fid,
                    image_path=dst,
                    time=i / max(n - 1, 1),
                    camera=Camera(K=K, viewmat=viewmat, width=width, height=height, distortion=dist),
                    exposure=exposure if cam_id == 0 else 0.0,
                    split="test" if held else "train",
                    camera_id=cam_id,
                )

            todo = [(nm, cam_id) for names, cam_id in ((names_a, 0), (names_b, 1)) for nm in names if nm in reg]
            frames = parallel_map(lambda job: write_frame(*job), todo, desc="undistort and write", progress=progress)
            timings["write"] = time.perf_counter() - t0
            timings["total"] = time.perf_counter() - t_start
            report.seconds = {k: round(v, 2) for k, v in timings.items()}
            pts = list(rec.points3D.values())
            _write_scene(
                tmp,
                out.name,
                frames,
                np.array([p.xyz for p in pts], float).reshape(-1, 3),
                np.array([p.color for p in pts], float).reshape(-1, 3) / 255.0,
                report,
                scores,
            )
            colmap_dir = tmp / "colmap" / "sparse" / "0"
            colmap_dir.mkdir(parents=True)
            rec.write(str(colmap_dir))
    return report


def _kept_rate(video: Path, stride: int) -> float | None:
    rate = frame_rate(video)
    return None if rate is None else round(rate / max(stride, 1), 6)


def _write_scene(
    root: Path, name: str, frames: list[Frame], points: np.ndarray, colors: np.ndarray, report: IngestReport, scores: dict
) -> None:
    scene = Scene(
        name=name,
        root=root,
        frames=sorted(frames, key=lambda f: (f.camera_id, f.time)),
        points=points,
        point_colors=colors,
        source_format="video",
    )
    scene.normalize()
    scene.extras = {
        "normalized": True,
        "normalization": scene.normalization.to_dict(),
        "ingest": {**asdict(report), "registered_fraction": report.registered_fraction, "sharpness": scores},
    }
    write_nerfies(scene, root)


def _ingest_fixed_camera(
    video: Path,
    out: Path,
    eval_video: Path | None,
    stride: int,
    stride_reason: str,
    max_frames: int | None,
    max_size: int | None,
    exposure: float,
    holdout_every: int,
    overwrite: bool,
    progress: bool,
) -> IngestReport:
    """A camera that does not move: every frame gets the same pinhole camera (a
    FIXED_CAMERA_FOV_DEG field of view), and the first frame's pixels, back-projected to depths
    between 2 and 4, are the starting points. No SfM runs, so nothing checks the assumption."""
    if eval_video is not None:
        raise SceneError("--fixed-camera takes one video (a second camera would need SfM to place it)")
    t0 = time.perf_counter()
    images = decode_video(video, stride, max_frames, max_size, progress)
    h, w = images[0].shape[:2]
    f = 0.5 * w / math.tan(math.radians(FIXED_CAMERA_FOV_DEG) / 2)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    rng = np.random.default_rng(0)
    ys, xs = rng.integers(0, h, 4000), rng.integers(0, w, 4000)
    depth = rng.uniform(2.0, 4.0, 4000)
    points = np.stack([(xs + 0.5 - K[0, 2]) / f * depth, (ys + 0.5 - K[1, 2]) / f * depth, depth], 1)
    colors = images[0][ys, xs].astype(float) / 255.0
    n = len(images)
    report = IngestReport(
        video=str(video),
        eval_video=None,
        frames=n,
        eval_frames=0,
        registered=n,
        eval_registered=0,
        mean_reprojection_error_px=0.0,
        points=len(points),
        mapper="fixed-camera",
        stride=stride,
        stride_reason=stride_reason,
        fps=_kept_rate(video, stride),
        holdout=f"same-camera interpolation: every {ordinal(holdout_every)} frame" if holdout_every else "none",
    )
    with atomic_directory(out, overwrite=overwrite) as tmp:
        (tmp / "rgb" / "1x").mkdir(parents=True)
        frames = []
        for i, img in enumerate(images):
            fid = f"c0_{i:05d}"
            dst = tmp / "rgb" / "1x" / f"{fid}.png"
            Image.fromarray(img).save(dst, compress_level=PNG_LEVEL)
            held = bool(holdout_every) and i % holdout_every == holdout_every // 2
            frames.append(
                Frame(
                    id=fid,
                    image_path=dst,
                    time=i / max(n - 1, 1),
                    camera=Camera(K=K, viewmat=np.eye(4), width=w, height=h),
                    exposure=exposure,
                    split="test" if held else "train",
                    camera_id=0,
                )
            )
        report.seconds = {"decode": round(time.perf_counter() - t0, 2), "total": round(time.perf_counter() - t0, 2)}
        _write_scene(tmp, out.name, frames, points, colors, report, {})
    return report
