"""Structure from motion for video frames, with pycolmap: features, sequential matching, and three
mappers that trade speed for robustness.

- `keyframes` (the default): incremental SfM on every 4th or 8th frame only, then every other
  frame posed by absolute-pose RANSAC against that model's points (through its verified matches
  to the frames posed before it, in passes), points triangulated from all frames, and one global
  bundle adjustment. Mapping cost grows with the keyframes, not with every frame: the
  incremental mapper's repeated global bundle adjustments are what made long clips slow.
- `global`: GLOMAP (`pycolmap.global_mapping`): rotation averaging and global positioning, fast
  and with the most self-consistent poses where it works, but it fails outright on some clips.
- `incremental`: COLMAP's incremental mapper, started from the sharpest half of the frames and
  then extended to all of them. The slowest, and the fallback when the others fail.

`auto` tries keyframes (a second seed when they fall short), keyframes twice as dense, then
incremental, and records every attempt; a keyframe model with a strong radial term or a loose
rig (a second camera that turns against the first) also gets the incremental mapper's, and the
tighter rig (else the better fit) is kept. Frames are named so that the
two synchronised videos interleave in time (`f00012_a`, `f00012_b`); sequential matching orders
images by name and, with `quadratic_overlap`, pairs each image with the ones 1, 2, 4, 8, ...
positions later (only those: COLMAP 4's quadratic overlap has no linear part). Keyframes
therefore sit on a power-of-two grid: every keyframe pair at one grid step is a matched pair
(sharpest-in-a-window keyframes left the keyframe graph disconnected).
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..job_options import MAPPERS  # noqa: E402,F401  (declared with ingest's options)
from ..progress import announce, progress_bar
from .register import cam_from_world, register_rest

MAX_REPROJECTION_ERROR_PX = 4.0
MIN_KEYFRAMES = 12  # fewer training keyframes than this: the step halves
# Keyframes every 8th frame where that leaves this many per camera and a second camera gives each
# its same-time twin, else every 4th: sparser keyframes map faster but fall apart more often
# without the twins (docs/data.md, "Ingest speed and pose quality").
LONG_CLIP_KEYFRAMES = 32
KEYFRAME_RETRY_SEED = 2  # auto maps keyframes that fell apart once more with this seed (run_sfm)
# A keyframe model whose radial term is stronger than this (|k1| of SIMPLE_RADIAL) gets auto a second
# model from the incremental mapper, and the one with the lower reprojection error is kept: a long
# focal length with strong pincushion and the true one with little distortion reproject almost
# alike, and the keyframe mapper settles in either (docs/data.md, "A second opinion on the lens").
STRONG_RADIAL = 0.25
# With a synchronised second camera: a model in which the second camera turns against the first
# by more than this over the clip (the rig's rotation spread, in pixels at the first camera's focal
# length) gets auto the incremental mapper's model too, and the tighter rig is kept. The cameras
# are fixed together, so a loose rig is a model that misplaces one of them (docs/data.md, "A
# second opinion on the lens").
LOOSE_RIG_PX = 6.0


@dataclass
class SfmResult:
    """The reconstruction that was kept, which mapper made it, and every attempt on the way."""

    rec: object  # pycolmap.Reconstruction: every registered image with its pose, and the points
    mapper: str
    attempts: list[dict] = field(default_factory=list)
    # The lens refit's probe on the keyframe model (`refine_lens`'s report), where the keyframes
    # mapper made the model and a probe was asked for: `refine_lens(rec, probe=...)` skips the
    # whole model's refit where the keyframes gained less than a refit needs to be kept.
    lens_probe: dict | None = None


def quiet_colmap() -> None:
    """COLMAP logs every registration and solver warning to stderr; the stages show their own
    progress, so keep only errors unless KGS_SFM_LOG=1 asks for everything."""
    import pycolmap

    pycolmap.logging.minloglevel = 0 if os.environ.get("KGS_SFM_LOG") == "1" else 2


def extract_and_match(db: Path, images: Path, names_a: list[str], names_b: list[str], progress: bool) -> dict:
    """SIFT features (one camera per video) and sequential matching into `db`. Returns timings."""
    import pycolmap

    quiet_colmap()
    timings = {}
    t0 = time.perf_counter()
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = 1600
    extraction.use_gpu = False
    chunk = 96  # extraction is called in chunks only so that the progress bar moves (each call costs ~0.1 s)
    with progress_bar(total=len(names_a) + len(names_b), desc="features", show=progress) as bar:
        for names in (names_a, names_b):  # one camera per video
            reader = pycolmap.ImageReaderOptions()
            for s in range(0, len(names), chunk):
                pycolmap.extract_features(
                    db,
                    images,
                    image_names=names[s : s + chunk],
                    camera_mode=pycolmap.CameraMode.SINGLE,
                    reader_options=reader,
                    extraction_options=extraction,
                    device=pycolmap.Device.cpu,
                )
                if reader.existing_camera_id < 0:  # later chunks join the camera the first one made
                    with _open_db(db) as d:
                        reader.existing_camera_id = d.read_image_with_name(names[0]).camera_id
                bar.update(len(names[s : s + chunk]))
    timings["features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = 12 if names_b else 8
    pairing.quadratic_overlap = True
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    # Neighbouring video frames share most of their matches, where the confidence rule needs a
    # handful of RANSAC trials: COLMAP's floor of 100 was most of matching's time, and a floor
    # of 20 verifies the same pairs (docs/data.md, "Ingest speed and pose quality").
    verification.ransac.min_num_trials = 20
    announce("matching")
    if progress:
        print(f"matching {len(names_a) + len(names_b)} frames (sequential, quadratic overlap)", flush=True)
    pycolmap.match_sequential(
        db, matching_options=matching, pairing_options=pairing, verification_options=verification, device=pycolmap.Device.cpu
    )
    timings["matching"] = time.perf_counter() - t0
    return timings


class _open_db:
    """`with _open_db(path) as db`: a pycolmap Database closed on exit."""

    def __init__(self, path: Path):
        import pycolmap

        self.db = pycolmap.Database.open(str(path))

    def __enter__(self):
        return self.db

    def __exit__(self, *exc):
        self.db.close()


def _largest(recs: dict):
    return max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None


def _pipeline_options(cls, names: list[str] | None = None, seed: int = 0):
    opts = cls()
    opts.num_threads = 2
    opts.random_seed = seed
    # The pipeline's seed does not reach its mapper and triangulator (the global pipeline has
    # no triangulator of its own).
    for part in ("mapper", "triangulation"):
        if hasattr(opts, part):
            getattr(opts, part).random_seed = seed
    if names is not None:
        opts.image_names = names
    return opts


def map_incremental(db: Path, images: Path, out: Path, scores: dict[str, float]):
    """COLMAP's incremental mapper, seeded with the sharpest half of the frames (blurry frames are
    where initialisation fails), then continued over every frame."""
    import pycolmap

    ranked = sorted(scores, key=scores.get, reverse=True)
    first = sorted(ranked[: max(8, len(ranked) // 2)])
    (out / "seed").mkdir(parents=True, exist_ok=True)
    recs = pycolmap.incremental_mapping(db, images, out / "seed", options=_pipeline_options(pycolmap.IncrementalPipelineOptions, first))
    if not recs:
        return None
    best = max(recs, key=lambda k: recs[k].num_reg_images())
    (out / "all").mkdir(parents=True, exist_ok=True)
    recs2 = pycolmap.incremental_mapping(
        db, images, out / "all", input_path=out / "seed" / str(best), options=_pipeline_options(pycolmap.IncrementalPipelineOptions)
    )
    return _largest(recs2) or recs[best]


def map_global(db: Path, images: Path, out: Path):
    """GLOMAP. It may write relative poses into the database: give it a copy."""
    import pycolmap

    local = out / "database.db"
    shutil.copyfile(db, local)
    recs = pycolmap.global_mapping(local, images, out, options=_pipeline_options(pycolmap.GlobalPipelineOptions))
    return _largest(recs)


def strong_radial(rec) -> float | None:
    """The largest |k1| of `rec`'s SIMPLE_RADIAL or RADIAL cameras when above STRONG_RADIAL, else None."""
    k1 = [abs(float(c.params[3])) for c in rec.cameras.values() if c.model_name in ("SIMPLE_RADIAL", "RADIAL")]
    return max(k1) if k1 and max(k1) > STRONG_RADIAL else None


def poses(rec) -> dict[str, np.ndarray]:
    """Image name -> 4x4 world-to-camera matrix, for every posed image of `rec`."""
    return {im.name: np.vstack([np.asarray(cam_from_world(im).matrix()), [0, 0, 0, 1]]) for im in rec.images.values() if im.has_pose}


def rotation_angle_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def rig_consistency(P: dict[str, np.ndarray]) -> tuple[float, float] | None:
    """(median rotation spread in degrees, baseline length coefficient of variation) of camera b
    (`fNNNNN_b.png`) relative to its same-time camera a over all times both are posed in `P`
    (`poses`); None below three such times."""
    rel = [P[n.replace("_a.", "_b.")] @ np.linalg.inv(M) for n, M in P.items() if n.endswith("_a.png") and n.replace("_a.", "_b.") in P]
    if len(rel) < 3:
        return None
    rel = np.stack(rel)
    U, _, Vt = np.linalg.svd(rel[:, :3, :3].mean(0))
    mean_rot = U @ Vt
    spread = np.median([rotation_angle_deg(mean_rot.T @ r) for r in rel[:, :3, :3]])
    length = np.linalg.norm(rel[:, :3, 3], axis=1)
    return float(spread), float(length.std() / max(length.mean(), 1e-12))


def rig_spread_px(rec) -> float | None:
    """The rig's rotation spread (`rig_consistency`) as pixels at the training camera's focal
    length, so that one limit holds at any size; None without three same-time pairs."""
    rig = rig_consistency(poses(rec))
    focal = [rec.cameras[im.camera_id].mean_focal_length() for im in rec.images.values() if im.name.endswith("_a.png")]
    return None if rig is None or not focal else float(np.radians(rig[0]) * np.median(focal))


def needs_second_opinion(rec) -> bool:
    """A keyframe model that auto sets against the incremental mapper's: a strong radial term, or
    a loose rig."""
    return strong_radial(rec) is not None or (rig_spread_px(rec) or 0.0) > LOOSE_RIG_PX


def reprojection_px(rec) -> float:
    """`rec`'s mean reprojection error in pixels, from its current cameras, poses and points."""
    rec.update_point_3d_errors()
    return float(rec.compute_mean_reprojection_error())


def _better(rec, fraction: float, best, min_registered: float) -> bool:
    """Whether `rec` (posing `fraction` of the training frames) beats `best`: more frames posed,
    or, where both pose enough, the tighter rig where both have one, else a lower mean
    reprojection error (two lenses can reproject alike; a rig held apart cannot be right)."""
    if fraction >= min_registered and best[1] >= min_registered:
        rigs = rig_spread_px(rec), rig_spread_px(best[0].rec)
        if None not in rigs:
            return rigs[0] < rigs[1]
        return reprojection_px(rec) < reprojection_px(best[0].rec)
    return fraction > best[1]


def keyframe_time_budget(keyframes: int) -> int:
    """Seconds the keyframe model may take: a healthy one takes 10-30 s for 150 keyframes here."""
    return int(30 + keyframes // 4)


def default_keyframe_step(frames: int, second_camera: bool) -> int:
    """The keyframe step for a clip of `frames` training frames, with or without a synchronised
    `second_camera` (LONG_CLIP_KEYFRAMES)."""
    return 8 if second_camera and frames / 8 >= LONG_CLIP_KEYFRAMES else 4


def keyframe_names(names_a: list[str], names_b: list[str], step: int) -> list[str]:
    """Every `step`-th training frame from the first, with its synchronised twin: a power-of-two
    step keeps neighbouring keyframes among the pairs that sequential matching verified."""
    twins = set(names_b)
    picked = names_a[::step]
    return sorted(picked + [n.replace("_a.", "_b.") for n in picked if n.replace("_a.", "_b.") in twins])


class KeyframesFellApart(RuntimeError):
    """The keyframes formed models, none with half of them: fragments, or one small model (the
    mapper's random seed decides this as much as the frames do: docs/data.md, "Ingest speed")."""


def map_keyframes(
    db: Path,
    images: Path,
    out: Path,
    names_a: list[str],
    names_b: list[str],
    step: int = 4,
    progress: bool = True,
    stages: dict | None = None,
    adjust: bool = True,
    seed: int = 0,
    lens_probe: dict | None = None,
):
    """Incremental SfM on the keyframes (the mapper's random `seed`), absolute pose for every other
    frame (`register.register_rest`), triangulation from all frames and (with `adjust`) one global bundle
    adjustment. None when the keyframes form no model; KeyframesFellApart when none of their
    models holds half of them. `stages` receives the seconds of each step, and the frames posed
    in each registration pass (`register_passes`); `lens_probe`, when given, the report of the
    lens refit's probe on the keyframe model (`refine_lens`, LENS_PROBE_ITERATIONS)."""
    import pycolmap

    stages = {} if stages is None else stages
    t0 = time.perf_counter()
    while step > 1 and len(names_a) / step < MIN_KEYFRAMES:  # a short clip: keyframes closer together
        step //= 2
    keyframes = keyframe_names(names_a, names_b, step)
    (out / "keyframes").mkdir(parents=True, exist_ok=True)
    opts = _pipeline_options(pycolmap.IncrementalPipelineOptions, keyframes, seed)
    # Small enough for a short clip's keyframes, large enough that the mapper discards a stray
    # fragment and tries another start instead of keeping it (3 kept 3-image fragments).
    opts.min_model_size = min(10, max(3, len(keyframes) // 2))
    # A keyframe graph that falls apart makes the mapper start model after model from new initial
    # pairs (196 discarded models in one 336 + 336 frame ingest, minutes instead of seconds).
    # Bounded: what it has by then is kept or, when too small, mapped again more densely.
    opts.max_runtime_seconds = keyframe_time_budget(len(keyframes))
    models = pycolmap.incremental_mapping(db, images, out / "keyframes", options=opts)
    model = _largest(models)
    stages["keyframes"] = time.perf_counter() - t0
    if model is None:
        return None
    if model.num_reg_images() < max(3, len(keyframes) // 2):
        raise KeyframesFellApart(
            f"the keyframes fell apart into {len(models)} model(s), the largest {model.num_reg_images()} of {len(keyframes)}"
        )
    if lens_probe is not None:
        from .lens import LENS_PROBE_ITERATIONS, refine_lens  # (lens.py builds on this module)

        # A quarter of the frames or fewer, so a fraction of the whole model's cost (0.5 s against
        # 7-14 s on a 672-frame clip); how far it predicts the whole refit: refine_lens, docs/data.md.
        t0 = time.perf_counter()
        lens_probe.update(refine_lens(model, iterations=LENS_PROBE_ITERATIONS)[1], images=model.num_reg_images())
        stages["lens_probe"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    posed = {im.name: (im.camera_id, cam_from_world(im)) for im in model.images.values() if im.has_pose}
    with _open_db(db) as d:
        by_name = {im.name: im for im in d.read_all_images()}
        rest = [n for n in names_a + names_b if n not in posed]
        more, passes = register_rest(d, model, [by_name[n] for n in rest], progress)
        posed.update(more)
        stages["register_passes"] = passes
        stages["register"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        # A reconstruction of every posed frame, its keypoints and poses; points triangulated
        # from all of them, then one bundle adjustment over everything.
        rec = pycolmap.Reconstruction()
        for cam in model.cameras.values():
            rec.add_camera_with_trivial_rig(cam)
        for name, (camera_id, pose) in sorted(posed.items()):
            if camera_id not in rec.cameras:
                continue  # the other video's camera never entered the keyframe model
            im = by_name[name]
            keypoints = np.asarray(d.read_keypoints(im.image_id))[:, :2].astype(np.float64)
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=name, keypoints=keypoints, camera_id=camera_id, image_id=im.image_id), pose
            )
    (out / "all").mkdir(parents=True, exist_ok=True)
    triangulation = _pipeline_options(pycolmap.IncrementalPipelineOptions)
    # One round of its point refinement, not COLMAP's five: the adjustment below refines points,
    # poses and lens together anyway, to the same error, faster. Its track merging stays: without
    # it the real clips trained worse at the sharp camera (docs/data.md, "Ingest speed and pose quality").
    triangulation.ba_global_max_refinements = 1
    rec = pycolmap.triangulate_points(rec, db, images, out / "all", options=triangulation)
    drop_outlier_points(rec)  # before the adjustment too: a few wild points would drag it
    stages["triangulate"] = time.perf_counter() - t0
    if adjust:
        t0 = time.perf_counter()
        # pycolmap's bundle_adjustment logs its two INFO lines whatever the level, and leaves
        # the level at 0 afterwards: quiet it again.
        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = True
        ba.refine_extra_params = True
        ba.print_summary = False
        # Five iterations reach the reprojection error of 10 and 25 (1.02 px on a 672-frame
        # clip) in 10 s against 17 and 44; without it, 1.07 px (docs/data.md, "Ingest speed and pose quality").
        ba.ceres.solver_options.max_num_iterations = 5
        use_iterative_schur(ba)
        pycolmap.bundle_adjustment(rec, ba)
        quiet_colmap()
        drop_outlier_points(rec)
        stages["adjust"] = time.perf_counter() - t0
    return rec


def use_iterative_schur(ba) -> None:
    """Solves `ba`'s linear systems by preconditioned conjugate gradients on the Schur complement.
    Ceres' automatic choice for 50-1,000 images is a sparse direct factorisation, which on a video's
    banded camera graph and two cores took 13.8 s for the five iterations over 672 frames, against
    4.3 s this way, to the same reprojection error (1.0076 / 1.0077 px; docs/data.md)."""
    from pycolmap._core import pyceres

    ba.ceres.auto_select_solver_type = False
    ba.ceres.solver_options.linear_solver_type = pyceres.LinearSolverType.ITERATIVE_SCHUR
    ba.ceres.solver_options.preconditioner_type = pyceres.PreconditionerType.SCHUR_JACOBI


def drop_outlier_points(rec, max_error_px: float = MAX_REPROJECTION_ERROR_PX) -> int:
    """Deletes the points whose mean reprojection error exceeds `max_error_px` (COLMAP's
    mapper filters at the same 4 px); returns how many went."""
    rec.update_point_3d_errors()
    bad = [pid for pid, p in rec.points3D.items() if not np.isfinite(p.error) or p.error > max_error_px]
    for pid in bad:
        rec.delete_point3D(pid)
    return len(bad)


def run_sfm(
    db: Path,
    images: Path,
    work: Path,
    names_a: list[str],
    names_b: list[str],
    scores: dict[str, float],
    mapper: str = "auto",
    min_registered: float = 0.95,
    keyframe_step: int | None = None,
    progress: bool = True,
    probe_lens: bool = False,
) -> SfmResult | None:
    """Maps the frames of `db` with `mapper`. `auto` tries keyframes (once more with another seed
    when they fall apart or pose too few frames), keyframes twice as dense, then incremental, and keeps
    the first model that poses at least `min_registered` of the training frames (else the one
    that posed the most); a keyframe model with a strong radial term or a loose rig
    (`needs_second_opinion`) is set against the incremental mapper's, the tighter rig (else the
    lower reprojection error) kept. Returns None when no mapper produced a model. With `probe_lens`, a
    keyframe model also gets the lens refit's probe (`SfmResult.lens_probe`)."""
    if mapper not in MAPPERS:
        raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got {mapper!r}")
    quiet_colmap()
    keyframe_step = keyframe_step or default_keyframe_step(len(names_a), bool(names_b))
    # auto: keyframes; when their model falls short, keyframes twice as dense (more overlap between
    # neighbours, still far cheaper than mapping every frame); then every frame incrementally.
    # Each entry: (mapper, keyframe step, the mapper's random seed).
    order = (
        (
            [("keyframes", keyframe_step, 0)]
            + ([("keyframes", keyframe_step // 2, 0)] if keyframe_step > 1 else [])
            + [("incremental", None, 0)]
        )
        if mapper == "auto"
        else [(mapper, keyframe_step, 0)]
    )
    attempts, best = [], None
    second_opinion = False  # a keyframe model that needs_second_opinion: the incremental mapper's, then stop
    while order:
        name, step, seed = order.pop(0)
        out = work / (f"sparse_{name}" + (f"_{step}_{seed}" if name == "keyframes" else ""))
        out.mkdir(parents=True, exist_ok=True)
        announce(f"mapping ({name})")
        if progress:
            print(
                f"mapping with the {name} mapper"
                + (f" (every {step} frames" + (f", seed {seed})" if seed else ")") if name == "keyframes" else ""),
                flush=True,
            )
        t0 = time.perf_counter()
        error, stages, probe = None, {}, ({} if probe_lens and name == "keyframes" else None)
        try:
            if name == "keyframes":
                rec = map_keyframes(db, images, out, names_a, names_b, step, progress, stages, seed=seed, lens_probe=probe)
            elif name == "global":
                rec = map_global(db, images, out)
            else:
                rec = map_incremental(db, images, out, scores)
        except KeyframesFellApart as exc:
            rec, error = None, str(exc)
        except RuntimeError as exc:  # pycolmap raises RuntimeError on a failed solve
            rec, error = None, str(exc)
        posed = {im.name for im in rec.images.values() if im.has_pose} if rec is not None else set()
        fraction = sum(n in posed for n in names_a) / max(len(names_a), 1)
        if mapper == "auto" and name == "keyframes" and seed == 0 and fraction < min_registered and (rec is not None or error is not None):
            # Whether a keyframe graph falls apart depends on the mapper's seed as much as on the
            # frames, and another seed costs seconds where the fallbacks cost minutes (docs/data.md,
            # "Ingest speed and pose quality"). Keyframes that formed no model (too few) are not retried.
            order.insert(0, (name, step, KEYFRAME_RETRY_SEED))
        attempts.append(
            {
                "mapper": name,
                **({"keyframe_step": step, "seed": seed} if name == "keyframes" else {}),
                "seconds": round(time.perf_counter() - t0, 2),
                "registered_fraction": round(fraction, 4),
                "outcome": error or ("no model" if rec is None else "ok"),
                **({"stages": {k: round(v, 2) if isinstance(v, float) else v for k, v in stages.items()}} if stages else {}),
            }
        )
        if rec is not None:
            attempts[-1]["reprojection_px"] = round(reprojection_px(rec), 4)
            if (spread := rig_spread_px(rec)) is not None:
                attempts[-1]["rig_spread_px"] = round(spread, 3)
        if rec is not None and (best is None or _better(rec, fraction, best, min_registered)):
            best = (SfmResult(rec=rec, mapper=name, lens_probe=probe or None), fraction)
        if second_opinion or rec is not None and fraction >= min_registered:
            if not second_opinion and mapper == "auto" and name == "keyframes" and needs_second_opinion(rec):
                order.insert(0, ("incremental", None, 0))
                second_opinion = True
                continue
            break
    if best is None:
        return None
    best[0].attempts = attempts
    return best[0]
