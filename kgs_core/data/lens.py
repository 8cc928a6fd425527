"""The lens refit after mapping (`refine_lens`): the mappers' SIMPLE_RADIAL camera refitted as
COLMAP's OPENCV model by one bundle adjustment, kept only when plausible and when it lowers the
reprojection error enough (docs/data.md, "Lens")."""

from __future__ import annotations

import time

import numpy as np

from .sfm import drop_outlier_points, quiet_colmap, use_iterative_schur

# The lens fitted after mapping: COLMAP's OPENCV model (fx, fy, cx, cy, k1, k2, p1, p2; the
# principal point stays fixed). The mappers fit SIMPLE_RADIAL (one focal length, one radial term),
# which cannot hold a camera whose pixels are not square or whose distortion is decentred: such a
# lens leaves a second camera's images misplaced against the first's (docs/real-footage.md, "The
# lens model").
LENS_MODEL = "OPENCV"
from ..job_options import LENSES  # noqa: E402,F401  (ingest's --lens: refit as LENS_MODEL, or keep the mappers' SIMPLE_RADIAL)

LENS_ITERATIONS = 10  # converged: more iterations change the error by under 0.1 % (docs/data.md, "Lens")
LENS_PROBE_ITERATIONS = 5  # ... the first of them a probe that may stop the refit early (refine_lens)
# A refitted lens is kept only inside these bounds (a degenerate fit runs away in one of them).
MAX_ASPECT_CHANGE = 0.1  # |fx / fy - 1|
MAX_DISTORTION = 1.0  # |k1|, |k2|
MAX_TANGENTIAL = 0.1  # |p1|, |p2|
# ... and only when it lowers the mean reprojection error by this fraction: four more parameters
# always fit a little better, and a lens the mappers' model describes should stay as it is.
MIN_LENS_GAIN = 0.03


def opencv_params(cam) -> list[float] | None:
    """`cam`'s parameters as the OPENCV model's (the same lens), or None for a model it does
    not contain."""
    name = cam.model_name
    p = [float(x) for x in cam.params]
    if name == "SIMPLE_PINHOLE":
        return [p[0], p[0], p[1], p[2], 0, 0, 0, 0]
    if name == "PINHOLE":
        return p + [0, 0, 0, 0]
    if name == "SIMPLE_RADIAL":
        return [p[0], p[0], p[1], p[2], p[3], 0, 0, 0]
    if name == "RADIAL":
        return [p[0], p[0], p[1], p[2], p[3], p[4], 0, 0]
    if name == "OPENCV":
        return p
    return None


def plausible_lens(params: list[float]) -> bool:
    fx, fy, _, _, k1, k2, p1, p2 = params
    return (
        fx > 0
        and fy > 0
        and abs(fx / fy - 1) <= MAX_ASPECT_CHANGE
        and max(abs(k1), abs(k2)) <= MAX_DISTORTION
        and max(abs(p1), abs(p2)) <= MAX_TANGENTIAL
    )


def lens_gain(report: dict) -> float | None:
    """The fraction of the reprojection error a lens refit (`refine_lens`'s report) removed; None
    where it has no result (a failed adjustment, a camera without an OPENCV equivalent)."""
    if "after_px" not in report:
        return None
    return 1 - report["after_px"] / max(report["before_px"], 1e-12)


def refine_lens(rec, iterations: int = LENS_ITERATIONS, probe: dict | None = None) -> tuple[object, dict]:
    """`(reconstruction, report)`: a copy of `rec` with every camera refitted as the OPENCV lens
    in one bundle adjustment, when that lowers the mean reprojection error by MIN_LENS_GAIN and
    every lens stays plausible; else `rec` itself. The report says what happened: `kept`,
    `model`, the errors `before_px` / `after_px`, the adjustment's `iterations` (fewer than
    asked where the probe stopped it), `seconds` and, when not kept, `reason`.

    `probe`: the same refit's report on a subset of the model (the keyframe model,
    `SfmResult.lens_probe`). Where it gained less than MIN_LENS_GAIN, the whole model is not
    refitted: the keyframe probe's gain follows the whole model's where both are small and
    exceeds it where they are large, so the whole refit would not be kept (docs/data.md,
    "Ingest speed and pose quality"; the report keeps the probe under `probe`)."""
    import pycolmap

    if iterations < 1:
        raise ValueError(f"iterations must be at least 1, got {iterations}")
    t0 = time.perf_counter()
    rec.update_point_3d_errors()  # (COLMAP caches each point's error; a model just built has none)
    before = float(rec.compute_mean_reprojection_error())
    report = {"model": LENS_MODEL, "before_px": round(before, 4), "kept": False}
    if probe is not None:
        report["probe"] = probe
    probed = None if probe is None else lens_gain(probe)
    if probed is not None and probed < MIN_LENS_GAIN:
        report.update(
            seconds=round(time.perf_counter() - t0, 2),
            reason=f"the keyframe model's refit lowered its error by {probed:.1%} in {probe['iterations']} "
            f"iterations, under {MIN_LENS_GAIN:.0%}: not tried on every frame",
        )
        return rec, report
    converted = {cid: opencv_params(cam) for cid, cam in rec.cameras.items()}
    if any(p is None for p in converted.values()):
        report["reason"] = "a camera model without an OPENCV equivalent"
        return rec, report
    trial = pycolmap.Reconstruction(rec)
    for cid, params in converted.items():
        cam = pycolmap.Camera.create_from_model_name(cid, LENS_MODEL, params[0], trial.cameras[cid].width, trial.cameras[cid].height)
        cam.params = params
        trial.cameras[cid] = cam
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = True
    ba.refine_extra_params = True
    ba.print_summary = False
    use_iterative_schur(ba)
    # A probe of LENS_PROBE_ITERATIONS first: where it gains less than a third of MIN_LENS_GAIN
    # the rest cannot reach it, and stopping there saves half the refit.
    done = 0
    for run in (min(LENS_PROBE_ITERATIONS, iterations), iterations - LENS_PROBE_ITERATIONS):
        if run <= 0:
            continue
        done += run
        ba.ceres.solver_options.max_num_iterations = run
        try:
            pycolmap.bundle_adjustment(trial, ba)
        except RuntimeError as exc:  # pycolmap raises RuntimeError on a failed solve
            report["reason"] = f"the adjustment failed: {exc}"
            return rec, report
        finally:
            quiet_colmap()
        drop_outlier_points(trial)  # a point or two may run off in the larger model
        after = float(trial.compute_mean_reprojection_error())
        if not np.isfinite(after) or after > (1 - MIN_LENS_GAIN / 3) * before:
            break
    report.update(after_px=round(after, 4), iterations=done, seconds=round(time.perf_counter() - t0, 2))
    lenses_ok = all(plausible_lens([float(x) for x in cam.params]) for cam in trial.cameras.values())
    if not np.isfinite(after) or after > (1 - MIN_LENS_GAIN) * before or not lenses_ok:
        report["reason"] = (
            "an implausible lens"
            if not lenses_ok
            else f"lowers the reprojection error by {1 - after / max(before, 1e-12):.1%}, under {MIN_LENS_GAIN:.0%}"
        )
        return rec, report
    report["kept"] = True
    return trial, report
