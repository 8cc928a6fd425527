"""Training configuration, the two presets and the ablation switches."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Literal

from ..device import Device
from ..model.config import ModelConfig
from ..schema import check_choices, from_fields, json_object
from .densify import DensifyStrategy
from .flow import FlowMethod

CameraBlur = Literal["off", "poses", "learned"]
FrameSampling = Literal["uniform", "loss"]
OnNonfinite = Literal["error", "restore"]
# The nested parts of the training schema: settings reach their fields as `PART.FIELD`.
NESTED = {"model": ModelConfig, "densify": DensifyStrategy}

ABLATIONS = {
    "cf": "no coarse-to-fine (dynamic Gaussians use the field's own offsets)",
    "kr": "no kinematic covariance refinement",
    "reg": "no L_reg",
    "ani": "no L_ani",
    "decompose": "no static/dynamic decomposition: every Gaussian deforms (also disables C.F. and K.R.)",
    "deform": "no deformation at all: a static 3DGS",
}


@dataclass
class TrainConfig:
    iterations: int = 3000
    # Seconds the training may take on this machine (0: none). Before training a short pilot picks
    # the iterations, and for a small budget the Gaussian budget, that fit (train/budget.py).
    time_budget: float = 0.0
    batch_size: int = 1
    # Coarse-to-fine images: the first `downscale_until` of the iterations train on frames
    # area-averaged by 2^downscales, halved at equal shares of it, full size after; per-pixel
    # work (rasteriser, SSIM) then costs a quarter per halving (0: full size throughout).
    downscales: int = 0
    downscale_until: float = 0.5
    seed: int = 0
    init_points: int = 20_000  # SfM points used to initialise (random subset when more)
    # learning rates (position: exponential decay from init to final; the rest constant)
    lr_means: float = 1.6e-4
    lr_means_final: float = 1.6e-6
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacity: float = 5e-2
    lr_sh0: float = 2.5e-3
    lr_sh_rest: float = 2.5e-3 / 20
    lr_features: float = 2.5e-3
    lr_grid: float = 1.6e-3
    lr_grid_final: float = 1.6e-5
    lr_deform: float = 1.6e-4
    lr_deform_final: float = 1.6e-6
    lr_kappa: float = 1e-2
    # densification (3DGS), pruning, opacity resets and the Gaussian budget
    densify: DensifyStrategy = field(default_factory=DensifyStrategy)
    # static/dynamic decomposition
    decompose_at: int = 3000  # end of the warm-up in which every Gaussian deforms
    decompose_every: int = 2000  # re-run the decomposition on this schedule (0 = never)
    # Each decomposition keeps every Gaussian where it renders on average (`KinematicsGS.decompose`,
    # in_place); False: Gaussians that change sides jump by their mean offset.
    decompose_in_place: bool = True
    # A re-decomposition may turn static Gaussians dynamic (True, the paper's re-decomposition), or only
    # dynamic ones static (False, fitted for video ingests: there the field's motion where a
    # static Gaussian sits, never fitted to it, is as often the unobservable motion of an
    # untextured wall as a moving object's; docs/method.md, "Decompositions in place").
    redecompose_to_dynamic: bool = True
    # True: each decomposition in training picks τ from the distribution of K (`otsu_tau`), never below
    # model.tau; False: model.tau as it is (given with --tau, the decomposition uses it).
    tau_auto: bool = True
    # Otsu's split (tau_auto) reads only the Gaussians whose K is above this share of model.tau:
    # those the field leaves (almost) still form a third mode that the split otherwise cut off
    # (docs/method.md, "Settings that follow the scene"). 0: every Gaussian.
    tau_auto_from: float = 0.01
    # losses
    lambda_dssim: float = 0.2
    lambda_reg: float = 1e-3
    # Static Gaussians drawn per step for L_reg's static term (the field's offsets under them,
    # `KinematicsGS.static_field_dx`, as the paper sums L_reg over the static set); 0 leaves it
    # out. Off by default: no gain measured, and slower (docs/real-footage.md).
    reg_static_samples: int = 0
    # A coarse photometric term: L1 between render and frame average-pooled by `coarse_factor`,
    # weighted `lambda_coarse` (0: off). It keeps a gradient on a moving object the field has
    # lost track of (losses.coarse_l1).
    lambda_coarse: float = 0.0
    coarse_factor: int = 8
    # L1 between the image differences of render and frame (losses.gradient_l1), weighted
    # `lambda_grad` (0: off): gives fine detail the share of the loss that blur takes from it.
    # Off in both presets: at 0.3 one synthetic decomposition collapsed (docs/method.md, "Fine detail").
    lambda_grad: float = 0.0
    # Optical flow between consecutive training frames asks the deforming Gaussians to move in
    # the image as their pixels do (train/flow.py; per pixel of disagreement, 0: off).
    # fit_to_scene turns it on for video ingests (VIDEO_FLOW_WEIGHT).
    lambda_flow: float = 0.0
    # Which optical flow the flow term and spawning read (train/flow.py): "dis", OpenCV's DIS
    # (its medium preset, which stops at half resolution); "dis_full", the same down to full
    # resolution; "fused", per pixel DIS or Farneback, whichever warps the next frame closer.
    # DIS gives a small object (a few of its 8 px patches) the motion around it; the other two
    # see it, but measured worse for the flow term and spawning, so DIS stays here; the decompositions'
    # reading has its own setting below (docs/real-footage.md, "A flow that sees small objects").
    flow_method: FlowMethod = "dis"
    # At each densification after the decomposition, the `spawn_frames` training frames with the highest
    # running loss (above 1.5x the median frame's) get up to `spawn_max` new dynamic Gaussians,
    # present for about `spawn_life` frames around their frame's time, at the pixels the render
    # still gets wrong where something moves on its own (train/spawn.py; 0: off). They bring
    # back a moving person the field lost track of. fit_to_scene turns it on for video ingests
    # (VIDEO_SPAWN_FRAMES; docs/real-footage.md, "Spawned Gaussians").
    spawn_frames: int = 0
    spawn_max: int = 200
    # Frame intervals: the width of the presence's Gaussian in time. Two, since spawned Gaussians
    # move on their own line (model.spawned_motion="own") and so stay right a frame or two away;
    # one measured better while they followed the field (docs/real-footage.md).
    spawn_life: float = 2.0
    spawn_from: float = 0.0  # no spawning before this fraction of the iterations (nor before the decomposition)
    lambda_ani: float = 1e-4
    eps_ani: float = 1e-6
    lambda_tv: float = 1e-4  # K-Planes smoothness
    # time noise (appendix B), in frame intervals
    noise_init_frames: float = 1.0
    noise_final_frames: float = 0.0
    noise_until: float = 0.75  # fraction of the iterations
    noise_delay: float = 0.05
    noise_w_delay: float = 0.1
    # True: each Gaussian draws its own time jitter; False: one shift of the frame's time for
    # all of them in a step (D3DGS's annealed smooth training).
    noise_per_gaussian: bool = True
    # Which training frame each step sees: "uniform", or "loss" (a mix of uniform and each
    # frame's running photometric loss, so that frames the model fits worst are seen more).
    frame_sampling: FrameSampling = "uniform"
    frame_sampling_mix: float = 0.5  # "loss": the share of draws weighted by the loss
    # The warm-up sees a time window that grows from the clip's middle: at iteration 0 the frames
    # within `time_window_start` / 2 of the middle (as a fraction of the clip), the whole clip
    # from three quarters of the warm-up (`decompose_at`) on. 1.0: the whole clip from the start.
    time_window_start: float = 1.0
    # FLoD
    lod_levels: int = 5
    lod_lambda: float = 0.02  # s_min of level 1, normalised scene units
    lod_rho: float = 0.5  # geometric decay per level
    lod_fractions: tuple = (0.1, 0.2, 0.35, 0.55, 1.0)  # where each level ends
    lod_importance_views: int = 16
    lod_prune_importance: float = 0.01
    # logging
    eval_every: int = 250
    eval_frames: int = 4
    checkpoint_every: int = 1000
    # guards: what a NaN/Inf in the loss or a gradient does
    on_nonfinite: OnNonfinite = "error"  # "error": stop, naming the tensor; "restore": last good checkpoint
    # Where training computes (kgs_core/device.py): "auto" takes CUDA when torch sees a GPU
    # (the rasteriser is then gsplat's, the `cuda` extra), else the CPU.
    device: Device = "auto"
    nonfinite_lr_factor: float = 0.5  # "restore" multiplies every learning rate by this
    nonfinite_max_restores: int = 3
    model: ModelConfig = field(default_factory=ModelConfig)
    ablate: tuple = ()
    # Blur every Gaussian along the camera's own motion during the exposure too (K.R. convolve
    # form only; train/camera_motion.py): "off", "poses" (central differences of the poses) or
    # "learned" (per-frame motion fitted from there, at lr_camera_motion). docs/method.md.
    camera_blur: CameraBlur = "off"
    lr_camera_motion: float = 3e-3
    # Fit a rigid correction of each training camera's pose (train/pose_refine.py). Off by
    # default: it fits the training views better and a second camera worse, in twice the time
    # (docs/real-footage.md).
    pose_refine: bool = False
    lr_pose: float = 1e-3
    lr_pose_final: float = 1e-5
    init_from: str = ""  # a run directory: start from its final model (fine-tuning), not from points
    # The training camera's exposure (fraction of the frame interval); None: the scene's own.
    exposure: float | None = None
    # Learn the exposure from the footage, starting from the one above (train/exposure.py):
    # one scalar fitted with the rest once K.R. acts (after the decomposition), at lr_exposure.
    fit_exposure: bool = False
    lr_exposure: float = 2e-2
    # At this fraction of the iterations (after the decomposition, so that K.R. has trained a while)
    # K.R.'s effect on the training renders is measured (`evaluate.kr_effect`), and K.R. is
    # turned off for the rest of the run when its blur does next to nothing: then its velocity
    # samples are pure cost (docs/real-footage.md, "What K.R.'s blur does on real footage").
    # 0 never checks.
    kr_check_at: float = 0.4
    # At every decomposition, a Gaussian that K calls static but that sits on pixels the optical flow
    # shows moving on their own, where no K-dynamic Gaussian draws, in at least this share of
    # the sampled training frames where it is visible, is called dynamic (train/flow_vote.py).
    # The field may not have learned a moving object's motion by the first decomposition (the synthetic
    # spinning top's arrives between 30 and 35 % of the run), and a Gaussian called static is
    # never moved by the field again. 0 turns it off (docs/real-footage.md, "The decompositions read
    # the flow").
    flow_vote_share: float = 0.1
    # The flow the decompositions' reading reads (the choices of `flow_method`). "dis_full" (DIS down
    # to full resolution, fitted on a video ingest) finds a small, fast object that DIS's
    # half-resolution search gives the motion around it (the synthetic `smallpanel`); it cost
    # the synthetic demo, so DIS stays for the rest. It computes 16
    # flows of its own when the run's differ (docs/real-footage.md, "A flow that sees small objects").
    flow_vote_method: FlowMethod = "dis"
    # What `fit_to_scene` chose from the scene and why ({setting: reason}); empty when the
    # preset's constants were kept (no scene given, or every setting given explicitly).
    fitted: dict = field(default_factory=dict)
    # A time budget's pilot ({"cost": StepCost, "most_gaussians": the preset's budget}), from
    # which the Gaussian budget is revised after the first decomposition (train/budget.py);
    # empty without a budget, or with a Gaussian budget given by hand.
    budget_pilot: dict = field(default_factory=dict)

    def __post_init__(self):
        check_choices(self)
        if self.budget_pilot:  # (a run.json's config may come from anywhere)
            from .budget import read_budget_pilot

            read_budget_pilot(self.budget_pilot)
        if not 0 <= self.flow_vote_share <= 1:
            raise ValueError(f"flow_vote_share must be a fraction in [0, 1], got {self.flow_vote_share}")
        if not 0 <= self.kr_check_at <= 1:
            raise ValueError(f"kr_check_at must be a fraction in [0, 1], got {self.kr_check_at}")
        if self.spawn_frames < 0 or self.spawn_max < 1 or not self.spawn_life > 0 or not 0 <= self.spawn_from <= 1:
            raise ValueError(
                f"spawn settings: spawn_frames >= 0, spawn_max >= 1, spawn_life > 0 (frames) and "
                f"0 <= spawn_from <= 1, got {self.spawn_frames!r}, {self.spawn_max!r}, "
                f"{self.spawn_life!r}, {self.spawn_from!r}"
            )
        if self.exposure is not None and not 0 <= self.exposure <= 1:
            raise ValueError(f"exposure must be in [0, 1] (a fraction of the frame interval), got {self.exposure!r}")
        if not self.lambda_flow >= 0:
            raise ValueError(f"lambda_flow must be >= 0, got {self.lambda_flow!r}")
        if not self.lambda_grad >= 0:
            raise ValueError(f"lambda_grad must be >= 0, got {self.lambda_grad!r}")
        if not self.lambda_coarse >= 0 or self.coarse_factor < 1:
            raise ValueError(
                f"lambda_coarse must be >= 0 and coarse_factor >= 1 (pixels), got {self.lambda_coarse!r} and {self.coarse_factor!r}"
            )

    def to_dict(self) -> dict:
        from ..migrations import CONFIG_VERSION

        d = asdict(self)
        d["model"] = self.model.to_dict()
        d["densify"]["opacity_reset_at"] = list(self.densify.opacity_reset_at)
        for k in ("lod_fractions", "ablate"):
            d[k] = list(d[k])
        return {"config_version": CONFIG_VERSION, **d}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """From `to_dict`'s output (a run.json's `config`) of any version (`kgs_core.migrations`);
        ValueError naming the field when a part is malformed (keys this version does not know
        are skipped at the top level, refused inside `model` and `densify`)."""
        from ..migrations import CONFIG_VERSION, migrate_config

        d = migrate_config(json_object(d, "config"))
        if "model" not in d:
            raise ValueError("config has no model block")
        m = d.pop("model")
        densify = d.pop("densify", None) or {}
        for k in ("lod_fractions", "ablate"):
            if k in d:
                d[k] = tuple(d[k])
        known = {f.name for f in fields(cls)} - {"model", "densify"}
        return cls(
            model=ModelConfig.from_dict({"config_version": CONFIG_VERSION, **m}),
            densify=from_fields(DensifyStrategy, densify, "densify."),
            **{k: v for k, v in d.items() if k in known},
        )


# Both presets' Gaussian budget on the 128² demo (fit_to_scene scales it with the pixel count):
# near the paper's own final counts, where an unbounded paper preset grew until a two-core step
# took seconds (docs/real-footage.md, "The paper preset on walk").
MAX_GAUSSIANS = 30_000


def paper_preset(iterations: int = 30_000) -> TrainConfig:
    """The paper as written (docs/method.md, "The paper preset", has each value beside the paper's
    words and what it leaves open): 30k iterations, batch 2, five FLoD levels, densification
    500-10k at gradient 1e-4 and opacity 0.005, an opacity reset at 3k; K > τ with τ = 2e-5
    fixed (no Otsu, no flow vote, plain re-decompositions); K.R. by eqs. 9-19 on the field's
    predicted Σ and r_z with v = δx_t / Δt; L_reg with its static term; the time noise
    annealed before the first decomposition; none of the product's additions (flow term,
    spawning, time opacity, the K.R. check, camera blur). Only the Gaussian budget
    (MAX_GAUSSIANS) is ours, for a two-core machine. Another iteration count scales every
    schedule point with it."""
    at = lambda i: max(1, round(i * iterations / 30_000))  # noqa: E731
    # A random start (a scene without SfM points) no larger than the budget, so that
    # densification has room from its first step.
    return TrainConfig(
        iterations=iterations,
        batch_size=2,
        init_points=MAX_GAUSSIANS,
        densify=DensifyStrategy(start=at(500), stop=at(10_000), opacity_reset_at=(at(3000),), max_gaussians=MAX_GAUSSIANS),
        decompose_at=at(3000),
        decompose_every=at(2000),
        decompose_in_place=False,
        redecompose_to_dynamic=True,
        tau_auto=False,
        flow_vote_share=0.0,
        reg_static_samples=PAPER_STATIC_SAMPLES,
        noise_until=0.1,  # converged by the first decomposition (appendix B)
        noise_delay=0.02,
        kr_check_at=0.0,
        model=ModelConfig(
            sh_degree=3,
            tau=2e-5,
            kr_form="paper",
            kr_inputs="predicted",
            velocity="paper",
            basis="paper",
            still_len=0.0,
            knn_radius=0.0,
            time_opacity=False,
        ),
        eval_every=at(1000),
        checkpoint_every=at(5000),
    )


# The static Gaussians whose field offsets L_reg's static term averages each step (a sample:
# static Gaussians render without the field, so their offsets cost an extra evaluation).
PAPER_STATIC_SAMPLES = 4096


FAST_ITERATIONS = 1500  # the fast preset's count on the demo scene (fitted_iterations scales it)


def fast_preset(iterations: int = FAST_ITERATIONS) -> TrainConfig:
    """Tuned to converge in minutes on two CPU cores at ~128 px: fewer iterations and
    Gaussians, SH degree 1, one LoD level (FLoD stays in the paper preset), everything else
    scaled to the shorter schedule (and to `iterations` when it is not the default 1,500;
    what doubling it buys: docs/method.md)."""
    it = iterations
    return TrainConfig(
        iterations=it,
        batch_size=1,
        init_points=8_000,
        lr_means=4e-4,
        lr_means_final=4e-6,
        densify=DensifyStrategy(
            start=max(1, it // 10),
            stop=int(0.7 * it),
            every=150,
            grad_threshold=2e-4,
            opacity_reset_at=(int(0.3 * it),),
            max_gaussians=MAX_GAUSSIANS,
        ),
        decompose_at=max(1, int(0.2 * it)),
        decompose_every=max(1, int(0.2 * it)),
        eval_every=max(1, it // 5),
        checkpoint_every=max(1, 2 * it // 3),
        lambda_tv=0.0,
        lambda_reg=1e-2,
        lod_levels=1,
        lod_fractions=(1.0,),  # five levels cost quality at this budget (docs/method.md)
        lr_deform=5e-3,
        lr_deform_final=5e-5,
        lr_grid=1e-2,
        lr_grid_final=1e-4,
        model=ModelConfig(sh_degree=1, deform_spatial=32, deform_temporal=16, deform_features=16, deform_multires=(1,)),
    )


PRESETS = {"fast": fast_preset, "paper": paper_preset}


def finetune_config(parent: TrainConfig, iterations: int, tau: float | None = None) -> "TrainConfig":
    """Fine-tuning a finished run (its configuration) for `iterations` more, keeping its decomposition
    (at `tau` when given): no densification, no re-decomposition, no opacity reset, one LoD level,
    full-size images, the position learning rate at its final value."""
    return replace(
        parent,
        iterations=iterations,
        densify=replace(parent.densify, start=iterations + 1, stop=0, opacity_reset_at=()),
        decompose_at=iterations + 1,
        decompose_every=0,
        lod_levels=1,
        lod_fractions=(1.0,),
        downscales=0,  # the parent has trained at full size
        lr_means=parent.lr_means_final,
        eval_every=max(iterations // 5, 1),
        checkpoint_every=iterations,
        time_window_start=1.0,  # the parent has seen the whole clip
        model=parent.model if tau is None else replace(parent.model, tau=tau),
    )


def check_ablations(ablate) -> None:
    """ValueError naming the first name that is not an ablation (and its new name if renamed)."""
    from ..migrations import ABLATION_RENAMES

    for a in ablate:
        if not isinstance(a, str) or a not in ABLATIONS:
            hint = f" ({a!r} is now called {ABLATION_RENAMES[a]!r})" if isinstance(a, str) and a in ABLATION_RENAMES else ""
            raise ValueError(f"unknown ablation {a!r}; one of {', '.join(ABLATIONS)}{hint}")


def make_config(preset: str = "fast", ablate: tuple = (), scene=None, plan_budget: bool = True, **overrides) -> TrainConfig:
    """The preset with the ablations and overrides applied, fitted to `scene` when given, and,
    with a `time_budget` and a scene (unless `plan_budget` is False), planned to fit it on this
    machine (`budget.fit_time_budget`, which runs a short pilot)."""
    from .fitting import fit_to_scene, fitted_iterations

    given = dict(overrides)
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(PRESETS)}")
    check_ablations(ablate)
    # The preset lays its schedule out for the iteration count (an explicit override of any
    # schedule point still wins).
    explicit = set(overrides)
    fitted = {}
    if scene is not None and preset == "fast" and "iterations" not in overrides:
        n, why = fitted_iterations(scene)
        if why:
            overrides, fitted = {**overrides, "iterations": n}, {"iterations": why}
    cfg = PRESETS[preset](**({"iterations": overrides["iterations"]} if "iterations" in overrides else {}))
    nested = {part: {k[len(part) + 1 :]: v for k, v in overrides.items() if k.startswith(part + ".")} for part in NESTED}
    cfg = replace(cfg, **{k: v for k, v in overrides.items() if k.split(".")[0] not in NESTED}, ablate=tuple(ablate))
    if nested["densify"]:
        cfg = replace(cfg, densify=replace(cfg.densify, **nested["densify"]))
    m = cfg.model
    if nested["model"]:
        m = replace(m, **nested["model"])
    if scene is not None:
        cfg = fit_to_scene(replace(cfg, model=m, fitted=fitted), scene, explicit, additions=preset != "paper")
        m = cfg.model
    if "cf" in ablate or "decompose" in ablate:
        m = replace(m, coarse_to_fine=False)
    if "kr" in ablate or "decompose" in ablate:
        m = replace(m, kinematic=False)
    if "reg" in ablate:
        cfg = replace(cfg, lambda_reg=0.0)
    if "ani" in ablate:
        cfg = replace(cfg, lambda_ani=0.0)
    from .settings import check_config  # (settings reads this module's schema)

    cfg = check_config(replace(cfg, model=m))
    if cfg.time_budget > 0 and scene is not None and plan_budget:
        from .budget import fit_time_budget

        preset_budget = cfg.densify.max_gaussians

        def remake(iterations: int, max_gaussians: int) -> TrainConfig:
            budget = {"densify.max_gaussians": max_gaussians} if max_gaussians != preset_budget else {}
            return make_config(preset, ablate, scene, plan_budget=False, **{**given, "iterations": iterations, **budget})

        cfg = fit_time_budget(cfg, scene, remake, explicit)
    return cfg
