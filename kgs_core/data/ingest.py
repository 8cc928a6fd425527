"""Video ingest: decode, subsample, score sharpness, structure-from-motion with pycolmap, and
write a Nerfies-layout scene.

Blurry frames are where COLMAP fails, so the model is built from the sharpest frames first and
the rest are registered into it afterwards. An optional second, synchronised video (the BARD-GS
protocol: a sharp camera beside the blurry one) is registered into the same model and becomes
the held-out test views. Frames are named so that both videos interleave in time
(`f00012_a`, `f00012_b`), which lets sequential matching pair the two cameras.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from ..io import atomic_directory
from .formats import write_nerfies
from .formats.colmap import camera_from_colmap
from .scene import Camera, Frame, Scene, SceneError
from .video import decode_video


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

    @property
    def registered_fraction(self) -> float:
        return self.registered / max(self.frames, 1)


def sharpness(img: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image: low for blurry frames."""
    g = img.astype(np.float32).mean(axis=-1)
    lap = g[1:-1, 2:] + g[1:-1, :-2] + g[2:, 1:-1] + g[:-2, 1:-1] - 4 * g[1:-1, 1:-1]
    return float(lap.var())


def run_sfm(work: Path, names_a: list[str], names_b: list[str], scores: dict[str, float],
            sharp_fraction: float, progress: bool) -> tuple[object, dict]:
    """Features, sequential matching and two-stage incremental mapping. Returns the largest
    reconstruction and timings."""
    import pycolmap

    db, images, sparse = work / "database.db", work / "images", work / "sparse"
    timings = {}
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 1600
    extraction.use_gpu = False
    for names in (names_a, names_b):  # one camera per video
        if names:
            pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                      extraction_options=extraction, device=pycolmap.Device.cpu)
    timings["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 12 if names_b else 8
    pairing.quadratic_overlap = True
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    timings["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ranked = sorted(scores, key=scores.get, reverse=True)
    first = sorted(ranked[: max(8, int(len(ranked) * sharp_fraction))])
    opts = pycolmap.IncrementalPipelineOptions()
    opts.image_names = first
    opts.num_threads = 2
    opts.random_seed = 0
    stage1 = sparse / "stage1"
    stage1.mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(db, images, stage1, options=opts)
    if not recs:
        raise SceneError("structure from motion found no initial model in the sharpest frames "
                         "(too little texture or parallax?)")
    best = max(recs, key=lambda k: recs[k].num_reg_images())
    # Stage 2: continue from the sharp model and register every frame.
    opts2 = pycolmap.IncrementalPipelineOptions()
    opts2.num_threads = 2
    opts2.random_seed = 0
    final = sparse / "final"
    final.mkdir(parents=True, exist_ok=True)
    recs2 = pycolmap.incremental_mapping(db, images, final, options=opts2, input_path=stage1 / str(best))
    timings["mapping"] = time.perf_counter() - t0
    pool = list(recs2.values()) or [recs[best]]
    rec = max(pool, key=lambda r: r.num_reg_images())
    return rec, timings


def undistort_frame(cam, image_path: Path):
    """(pinhole pycolmap camera, undistorted RGB uint8 array) for one distorted frame."""
    import pycolmap

    bitmap = pycolmap.Bitmap.from_array(np.asarray(Image.open(image_path).convert("RGB")))
    pixels, pinhole = pycolmap.undistort_image(pycolmap.UndistortCameraOptions(), bitmap, cam)
    return pinhole, np.ascontiguousarray(pixels.to_array()[..., :3])


def ingest(video: str | Path, out: str | Path, eval_video: str | Path | None = None, every: int = 1,
           max_frames: int | None = None, max_size: int | None = 960, exposure: float = 0.5,
           sharp_fraction: float = 0.5, min_registered: float = 0.3, overwrite: bool = False,
           undistort: bool = True, progress: bool = True) -> IngestReport:
    """Builds a scene folder from a video. `exposure` is the assumed shutter fraction of the
    training video (unknown from the file; 0.5 is typical for indoor hand-held footage).

    With `undistort` (the default) every frame whose SfM camera has lens distortion is
    resampled to a pinhole camera by pycolmap's undistorter (cropped to valid pixels), since
    the rasteriser is pinhole; the distorted model stays under `colmap/sparse/0`."""
    video = Path(video)
    if not 0 <= exposure <= 1:
        raise SceneError(f"exposure must be in [0, 1], got {exposure}")
    t_start = time.perf_counter()
    frames_a = decode_video(video, every, max_frames, max_size, progress)
    frames_b: list[np.ndarray] = []
    if eval_video is not None:
        frames_b = decode_video(Path(eval_video), every, max_frames, max_size, progress)
        if len(frames_b) != len(frames_a):
            raise SceneError(f"frame counts differ: {video} has {len(frames_a)}, {eval_video} has {len(frames_b)} "
                             "(synchronised videos must have one frame per time step)")
    decode_s = time.perf_counter() - t_start
    n = len(frames_a)
    with tempfile.TemporaryDirectory(prefix="kgs-sfm-") as tmpdir:
        work = Path(tmpdir)
        (work / "images").mkdir()
        names_a, names_b, scores = [], [], {}
        for i, img in enumerate(frames_a):
            name = f"f{i:05d}_a.png"
            Image.fromarray(img).save(work / "images" / name)
            names_a.append(name)
            scores[name] = sharpness(img)
        for i, img in enumerate(frames_b):
            name = f"f{i:05d}_b.png"
            Image.fromarray(img).save(work / "images" / name)
            names_b.append(name)
            scores[name] = sharpness(img)
        rec, timings = run_sfm(work, names_a, names_b, scores, sharp_fraction, progress)
        timings["decode"] = decode_s
        reg = {im.name: im for im in rec.images.values() if im.has_pose}
        n_a = sum(1 for nm in names_a if nm in reg)
        n_b = sum(1 for nm in names_b if nm in reg)
        if n_a < max(2, min_registered * n):
            raise SceneError(f"structure from motion registered only {n_a} of {n} frames of {video} "
                             f"(need {min_registered:.0%}); try a slower subsample (--every) or more texture")
        report = IngestReport(
            video=str(video), eval_video=str(eval_video) if eval_video else None, frames=n, eval_frames=len(frames_b),
            registered=n_a, eval_registered=n_b, mean_reprojection_error_px=float(rec.compute_mean_reprojection_error()),
            points=rec.num_points3D(), seconds={k: round(v, 2) for k, v in timings.items()},
        )
        out = Path(out)
        with atomic_directory(out, overwrite=overwrite) as tmp:
            (tmp / "rgb" / "1x").mkdir(parents=True)
            frames = []
            for names, cam_id in ((names_a, 0), (names_b, 1)):
                for nm in names:
                    if nm not in reg:
                        continue
                    im = reg[nm]
                    i = int(nm[1:6])
                    cam = rec.cameras[im.camera_id]
                    K, dist = camera_from_colmap(cam, f"{video}: SfM camera")
                    width, height = int(cam.width), int(cam.height)
                    if undistort and np.any(dist != 0):
                        cam, pixels = undistort_frame(cam, work / "images" / nm)
                        K, dist = camera_from_colmap(cam, f"{video}: undistorted camera")
                        width, height = int(cam.width), int(cam.height)
                        Image.fromarray(pixels).save(work / "images" / nm)
                    viewmat = np.eye(4)
                    cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
                    viewmat[:3] = np.asarray(cfw.matrix())
                    fid = f"c{cam_id}_{i:05d}"
                    dst = tmp / "rgb" / "1x" / f"{fid}.png"
                    shutil.copyfile(work / "images" / nm, dst)
                    frames.append(Frame(id=fid, image_path=dst, time=i / max(n - 1, 1),
                                        camera=Camera(K=K, viewmat=viewmat, width=width, height=height, distortion=dist),
                                        exposure=exposure if cam_id == 0 else 0.0, split="train" if cam_id == 0 else "test",
                                        camera_id=cam_id))
            pts = list(rec.points3D.values())
            scene = Scene(name=out.name, root=tmp, frames=sorted(frames, key=lambda f: (f.camera_id, f.time)),
                          points=np.array([p.xyz for p in pts], float).reshape(-1, 3),
                          point_colors=np.array([p.color for p in pts], float).reshape(-1, 3) / 255.0,
                          source_format="video")
            scene.normalize()
            scene.extras = {"normalized": True, "normalization": scene.normalization.to_dict(),
                            "ingest": {**asdict(report), "registered_fraction": report.registered_fraction,
                                       "sharpness": {k: round(v, 2) for k, v in scores.items()}}}
            write_nerfies(scene, tmp)
            colmap_dir = tmp / "colmap" / "sparse" / "0"
            colmap_dir.mkdir(parents=True)
            rec.write(str(colmap_dir))
    return report
