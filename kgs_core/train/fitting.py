"""The settings fitted to a scene instead of constants (`fit_to_scene`, `fitted_iterations`):
the fast preset is tuned on the demo scene, and these carry its choices to a clip of another
size, speed and kind (real footage). Each choice and its reason go into `TrainConfig.fitted`.
"""

from __future__ import annotations

import math
from dataclasses import replace

from .config import FAST_ITERATIONS, TrainConfig
from .scene_measures import camera_blur_px, scene_pixels_per_unit

# The fast preset's constants are tuned on the 128², 60-frame demo scene; these are that scene's
# size, against which fit_to_scene scales a clip's schedule and budget.
REFERENCE_PIXELS = 128 * 128
REFERENCE_FRAMES = 60
# What τ means on the demo scene: 2e-5 (normalised scene units²) is an RMS image motion of
# 0.62 px there. fit_to_scene converts this into each scene's units, so that "dynamic" means the
# same image motion on every scene (docs/method.md).
TAU_RMS_PX = 0.62
# FLoD's first-level minimum scale as a fraction of the image width (the paper preset's 0.02
# normalised units on the demo scene): in scene units it does not transfer, and on real footage
# the levels that densify would keep every Gaussian many pixels wide (docs/real-footage.md,
# "The paper preset on walk").
LOD_LAMBDA_WIDTH = 0.0217
MAX_ITERATION_SCALE = 4.0
# The coarse-to-fine images' smallest level (`downscales`) is at least this wide: frames twice
# as wide or more start at a half (a quarter, ...) of their size, where a step's per-pixel work
# costs a quarter, and reach full size halfway (docs/method.md, "Coarse-to-fine images").
COARSE_MIN_WIDTH = 400
# A video ingest at full size (frames at least twice COARSE_MIN_WIDTH wide) trains within this
# many seconds per training frame on this machine unless iterations or a time budget are given:
# the budget's plan picks the iterations and the Gaussian budget (train/budget.py). The preset's
# pixel-scaled schedule takes far longer there and scored no better at the sharp camera
# (docs/real-footage.md, "Full size in minutes").
SECONDS_PER_FRAME = 3.5
MIN_DEFAULT_BUDGET = 120  # seconds: a short clip's budget still fits a useful run
# The flow term's weight on real footage (a video ingest): the best of the weights measured,
# at no extra time; a larger one pulls the person off the photometric fit (docs/real-footage.md,
# "An optical-flow term").
VIDEO_FLOW_WEIGHT = 0.003
# Frames that get spawned Gaussians at each densification on real footage (a video ingest).
# Spawning puts the person back where the field lost him. Six frames rather than two: with two,
# the few worst frames took every turn and the clip's last frames, almost as badly fitted, never
# got one (docs/real-footage.md, "Spawned Gaussians", "Six frames a densification").
VIDEO_SPAWN_FRAMES = 6
# The camera's own blur (`camera_blur_px`) from which a scene models it (`camera_blur` =
# "learned"): below it the streak is within a pixel's own footprint and modelling it changed
# nothing but the time (docs/method.md, "The camera's own blur").
CAMERA_BLUR_MIN_PX = 0.5


def fitted_iterations(scene, iterations: int = FAST_ITERATIONS) -> tuple[int, str | None]:
    """The fast preset's iteration count for `scene`: the demo's scaled by the square root of
    the clip's frames x pixels over the demo's (1x to 4x), and the reason (None: unchanged)."""
    cam = scene.train_frames[0].camera
    n_frames, pixels = len(scene.train_frames), cam.width * cam.height
    scale = min(MAX_ITERATION_SCALE, max(1.0, (n_frames * pixels / (REFERENCE_FRAMES * REFERENCE_PIXELS)) ** 0.5))
    if scale == 1.0:
        return iterations, None
    n = int(round(iterations * scale, -1))
    return n, (f"{n}: {n_frames} frames of {cam.width}x{cam.height} are {scale:.2f}^2 times the demo's {REFERENCE_FRAMES} of 128x128")


def fit_to_scene(cfg: TrainConfig, scene, explicit: set[str], additions: bool = True) -> TrainConfig:
    """The settings that follow the scene instead of a constant, each skipped when given in
    `explicit` (so the command line can override every choice); each choice and its reason go
    into `cfg.fitted`, which run.json keeps. (The fast preset's iteration count is fitted
    before the preset lays out its schedule: `fitted_iterations`.) `additions=False` (the paper
    preset) fits only the Gaussian budget and FLoD's first scale, which the paper leaves open.

    * densify.max_gaussians: the preset's budget scaled by the square root of the pixel count
      at full size (frames at least twice COARSE_MIN_WIDTH wide, where the time budget's plan
      then picks the count under it) and for the paper preset; the preset's own below full size;
    * downscales: coarse-to-fine images for frames at least twice COARSE_MIN_WIDTH wide;
    * time_budget: SECONDS_PER_FRAME a training frame for a video ingest at full size, unless
      iterations or a budget were given (make_config then plans the run to fit it);
    * model.deform_temporal: at least one temporal cell per four frames;
    * model.tau: the demo's RMS image motion (TAU_RMS_PX) in this scene's units;
    * lod_levels: one on a video ingest (real footage), where FLoD's coarse levels misplace
      what moves at a second camera (docs/real-footage.md, "Why it loses on kitchen: FLoD");
    * lod_lambda (with more than one FLoD level): the first level's minimum scale as the same
      fraction of the image width as on the demo (LOD_LAMBDA_WIDTH), in this scene's units;
    * init_points: every SfM point of a video ingest (up to the Gaussian budget), not the
      preset's random subset (docs/real-footage.md, "Every SfM point");
    * lambda_flow: VIDEO_FLOW_WEIGHT on a video ingest (real footage), where the photometric
      loss alone loses moving objects (docs/real-footage.md, "An optical-flow term");
    * spawn_frames: VIDEO_SPAWN_FRAMES on a video ingest, which brings back the moving objects
      the field still loses (docs/real-footage.md, "Spawned Gaussians");
    * redecompose_to_dynamic: False on a video ingest (docs/method.md, "Decompositions in place");
    * camera_blur: "learned" where the training camera's own streak during the exposure
      (`camera_blur_px`, any scene with an exposure: a video ingest's, a synthetic scene's
      shaky camera) reaches CAMERA_BLUR_MIN_PX: the render is blurred along the camera's
      motion as the footage is, and the model stays sharp;
    * model.time_opacity: on for a video ingest, where the field leaves ghosts of what it
      could not follow (docs/real-footage.md, "Opacity that varies in time")."""
    n_frames = len(scene.train_frames)
    cam = scene.train_frames[0].camera
    pixels = cam.width * cam.height
    fitted = dict(cfg.fitted)
    full_size = cam.width >= 2 * COARSE_MIN_WIDTH  # (frames at the size BARD-GS and users film)
    # At full size the time budget's plan picks the count below this bound; below full size the
    # preset's own count held the quality at less time (docs/real-footage.md, "Below full size").
    if "densify.max_gaussians" not in explicit and pixels > REFERENCE_PIXELS:
        if full_size or not additions:
            budget = int(round(cfg.densify.max_gaussians * (pixels / REFERENCE_PIXELS) ** 0.5, -3))
            cfg.densify = replace(cfg.densify, max_gaussians=budget)
            fitted["densify.max_gaussians"] = f"{budget}: the preset's budget x sqrt({pixels} px / 128^2)"
        else:
            fitted["densify.max_gaussians"] = (
                f"{cfg.densify.max_gaussians}: the preset's budget, not scaled to {pixels} px below full size "
                "(--set densify.max_gaussians=N for more)"
            )
    m = cfg.model
    ppu = scene_pixels_per_unit(scene)
    if "lod_lambda" not in explicit and cfg.lod_levels > 1 and ppu is not None:
        px = LOD_LAMBDA_WIDTH * cam.width
        cfg.lod_lambda = float(f"{px / ppu:.3g}")
        fitted["lod_lambda"] = (
            f"{cfg.lod_lambda:.3g}: FLoD's first level at a minimum scale of {px:.1f} px "
            f"({LOD_LAMBDA_WIDTH:.2%} of the image width, as on the demo) at {ppu:.0f} px per "
            "scene unit"
        )
    if not additions:
        cfg.fitted = fitted
        return cfg
    if "downscales" not in explicit and cfg.downscales == 0 and full_size:
        cfg.downscales = int(math.log2(cam.width / COARSE_MIN_WIDTH))
        k = 2**cfg.downscales
        fitted["downscales"] = (
            f"{cfg.downscales}: {cam.width}x{cam.height} frames; the first "
            f"{cfg.downscale_until:.0%} of the iterations start on them at 1/{k} of the size "
            f"({cam.width // k} px wide, at least {COARSE_MIN_WIDTH}), where a step's per-pixel work "
            "costs far less (--set downscales=0 trains at full size throughout)"
        )
    video = "ingest" in scene.extras and n_frames > 1
    if video and full_size and cfg.time_budget == 0 and not {"iterations", "time_budget"} & explicit:
        cfg.time_budget = max(MIN_DEFAULT_BUDGET, round(SECONDS_PER_FRAME * n_frames))
        fitted["time_budget"] = (
            f"{cfg.time_budget} s ({SECONDS_PER_FRAME:g} s for each of {n_frames} frames, at least "
            f"{MIN_DEFAULT_BUDGET}): a video ingest "
            f"at full size ({cam.width}x{cam.height}) trains within a time on this machine (--iterations "
            "or --time-budget instead)"
        )
    if "model.deform_temporal" not in explicit and m.deform_temporal < n_frames // 4:
        cfg.model = m = replace(m, deform_temporal=min(n_frames // 4, 128))
        fitted["model.deform_temporal"] = f"{m.deform_temporal}: one temporal cell per four of {n_frames} frames"
    if "model.tau" in explicit and "tau_auto" not in explicit:
        cfg.tau_auto = False  # a τ given by hand is the τ used
    if "model.tau" not in explicit and ppu is not None:
        cfg.model = m = replace(m, tau=float(f"{(TAU_RMS_PX / ppu) ** 2:.3g}"))
        fitted["model.tau"] = (
            f"{m.tau:.3g}: an RMS image motion of {TAU_RMS_PX} px at {ppu:.0f} px per scene unit "
            "(median focal length over median point depth)"
        )
    if not {"lod_levels", "lod_fractions"} & explicit and cfg.lod_levels > 1 and video:
        cfg.lod_levels, cfg.lod_fractions = 1, (1.0,)
        fitted["lod_levels"] = (
            "1: a video ingest; FLoD's coarse levels misplaced a real clip's moving person at the "
            "second camera and the finer levels kept it there (docs/real-footage.md; "
            "--set lod_levels=5 keeps the paper's five)"
        )
    if "init_points" not in explicit and video and len(scene.points) > cfg.init_points:
        cfg.init_points = min(len(scene.points), cfg.densify.max_gaussians)
        fitted["init_points"] = (
            f"{cfg.init_points}: a video ingest; every SfM point ({len(scene.points)}) up to the "
            "Gaussian budget: a random subset left parts of the surfaces for densification to "
            'find, and the result varied with the seed (docs/real-footage.md, "Every SfM point")'
        )
    if "lambda_flow" not in explicit and cfg.lambda_flow == 0 and video:
        cfg.lambda_flow = VIDEO_FLOW_WEIGHT
        fitted["lambda_flow"] = (
            f"{VIDEO_FLOW_WEIGHT}: a video ingest; optical flow between its frames guides the "
            "moving Gaussians (--set lambda_flow=0 turns it off)"
        )
    if "spawn_frames" not in explicit and cfg.spawn_frames == 0 and video:
        cfg.spawn_frames = VIDEO_SPAWN_FRAMES
        fitted["spawn_frames"] = (
            f"{VIDEO_SPAWN_FRAMES}: a video ingest; the worst-fitted frames get new dynamic "
            "Gaussians where something moving is still missing (--set spawn_frames=0 turns "
            "it off)"
        )
    if "flow_vote_method" not in explicit and cfg.flow_vote_method == "dis" and video:
        cfg.flow_vote_method = "dis_full"
        fitted["flow_vote_method"] = (
            "dis_full: a video ingest; the decompositions read DIS's flow down to full resolution, "
            "which sees a small, fast object that its half-resolution search misses "
            "(--set flow_vote_method=dis keeps DIS's medium preset)"
        )
    if "redecompose_to_dynamic" not in explicit and cfg.redecompose_to_dynamic and video:
        cfg.redecompose_to_dynamic = False
        fitted["redecompose_to_dynamic"] = (
            "False: a video ingest; a re-decomposition turns no static Gaussian dynamic, since "
            "the field's motion where it sits was never fitted to it "
            "(--set redecompose_to_dynamic=true allows it)"
        )
    # (Only the convolve form of K.R. carries the camera's blur, and only after a decomposition.)
    blurs = m.kr_form == "convolve" and not {"decompose", "deform"} & set(cfg.ablate)
    streak = camera_blur_px(scene, cfg.exposure) if blurs and "camera_blur" not in explicit else None
    if cfg.camera_blur == "off" and streak is not None and streak >= CAMERA_BLUR_MIN_PX:
        cfg.camera_blur = "learned"
        fitted["camera_blur"] = (
            f"learned: the training camera draws a {streak:.1f} px streak during the "
            "exposure (median), which the render must blur by to match the footage, so that the "
            "model itself can be sharp (--camera-blur off turns it off)"
        )
    if "model.time_opacity" not in explicit and not m.time_opacity and video:
        cfg.model = m = replace(m, time_opacity=True)
        fitted["model.time_opacity"] = (
            "True: a video ingest; the dynamic Gaussians' opacity varies in time, so "
            "that the loss can fade a ghost the field leaves (--set "
            "model.time_opacity=false turns it off)"
        )
    cfg.fitted = fitted
    return cfg
