"""What the REST API answers, as pydantic models: the routers declare them as `response_model`,
so `/docs` shows each response's fields, and a handler that returns a field the model does not
list (or the wrong type) fails loudly in the tests instead of drifting from the documentation
(`extra="forbid"`). Request bodies live beside their routers; WebSocket messages in
`messages.py`."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field

from .registry import JobStatus


class Response(BaseModel):
    model_config = ConfigDict(extra="forbid")


class JobRow(Response):
    """What every registry row answers with: scenes, runs and exports are made by jobs."""

    id: str
    status: JobStatus
    error: str | None
    created: float = Field(description="Unix time")
    queue_position: int | None = Field(
        None, description="while queued behind other jobs (the server runs as many at once as it has cores): 1 for the next to start"
    )


# ------------------------------------------------------------------ system


class SystemInfo(Response):
    version: str
    workspace: str = Field(description="the workspace folder's name")
    scenes: int
    runs: int
    demo_scene: str = Field(description="the built-in scene `POST /api/demo` synthesizes")
    token_required: bool


class DemoStarted(Response):
    scene_id: str
    run_id: str


# ------------------------------------------------------------------ scenes


class StageProgress(Response):
    """A job's current stage (`backend/worker.py: stage_writer`): ingests and exports."""

    stage: str
    done: int
    total: int | None
    elapsed: float = Field(description="seconds since the job started")
    stages: list[tuple[str, float]] = Field(description="the stages done, each with its seconds")


class SceneSummary(JobRow):
    name: str
    source: str = Field(description="synth, ingest or upload")
    videos: int | None = Field(None, description="ingest scenes: the videos uploaded (1, or 2 with a sharp camera)")
    progress: StageProgress | None = None


class SceneDetail(SceneSummary):
    """A ready scene adds what its frames are (`kgs_core.data.scene.Scene`)."""

    frames: int | None = None
    train_frames: int | None = None
    test_frames: int | None = None
    image_size: tuple[int, int] | None = None
    dt: float | None = Field(None, description="the frame interval in normalised time")
    exposure: float | None = None
    format: str | None = None
    has_ground_truth: bool | None = None


# ------------------------------------------------------------------ runs


class TrainingProgress(Response):
    """A training job's latest step (`progress.json`, written by the job's process)."""

    iteration: int
    iterations: int
    loss: float | None
    psnr_heldout: float | None
    elapsed: float
    gaussians: int
    dynamic_share: float


class RunSummary(JobRow):
    scene_id: str | None
    name: str
    scene_name: str | None
    folder: str = Field(description="the run's folder, its last two path parts")
    progress: TrainingProgress | None
    has_model: bool
    resumable: bool = Field(description="stopped short of its iterations with a checkpoint to continue from")
    iteration: int | None = None
    train_seconds: float | None = None
    final_psnr_heldout: float | None = None
    gaussians: int | None = None
    dynamic_share: float | None = None
    lod_levels: int | None = None


class EditHistory(Response):
    undo: str | None = Field(description="the label of the step an undo reverts (None: nothing to undo)")
    undo_steps: int
    redo: str | None
    redo_steps: int


class ObjectSelection(Response):
    indices: list[int] = Field(description="the object's Gaussians (indices within the LoD level)")
    lod: int
    reach: float = Field(
        description="two Gaussians joined when their centres were at most this many times the "
        "sum of their largest standard deviations apart"
    )


class Decomposition(Response):
    """The static/dynamic decomposition at the run's live τ, with what the edit layer keeps."""

    tau: float
    lod: int
    gaussians: int
    dynamic: int
    static: int
    dynamic_share: float
    spawned: int = Field(description="Gaussians present for part of the clip (spawned in training), all dynamic")
    kept: int
    dynamic_kept: int
    static_kept: int
    history: EditHistory | None = Field(None, description="what undo and redo would revert, and how many steps each has")
    version: int = Field(description="bumped by every τ change or edit; splat buffers carry it")


class Histogram(Response):
    log10_edges: list[float] = Field(description="bin edges of log10 K")
    counts: list[int]


class Level(Response):
    level: int
    gaussians: int


class FrameInfo(Response):
    index: int
    id: str | int
    time: float
    split: str = Field(description="train or test")
    width: int
    height: int
    K: list[list[float]] = Field(description="3x3 intrinsics, pixels")
    viewmat: list[list[float]] = Field(description="4x4 world-to-camera, OpenCV axes")


class EditLevel(Response):
    deleted: list[int]
    hidden: list[int]


class Crop(Response):
    min: tuple[float, float, float]
    max: tuple[float, float, float]


class Edits(Response):
    """The run's edit layer (`kgs_core/edits.py`): per LoD level, by Gaussian index."""

    format_version: int
    levels: dict[str, EditLevel]
    crop: Crop | None
    history: dict | None = Field(None, description="earlier and undone layers, oldest first: {undo: [{label, layer}], redo: [...]}")


class CameraShake(Response):
    """The camera's own motion within one training frame's exposure (`train/camera_motion.py`):
    a still world point `x` moves relative to that camera like `(w × x + b)` per unit of
    normalised time."""

    t: float = Field(description="the training frame's normalised time")
    w: list[float] = Field(min_length=3, max_length=3, description="angular velocity")
    b: list[float] = Field(min_length=3, max_length=3, description="linear part")


class LearnedBlur(Response):
    objects: bool = Field(description="K.R.'s blur along each moving Gaussian's motion acts in this run")
    camera: str = Field(description="the camera's own blur: off, poses or learned")
    note: str
    camera_motion: list[CameraShake] | None = Field(
        None, description="the learned shake per training frame, in time order; an 'as captured' view applies the nearest"
    )


class RunDetail(RunSummary):
    """A run with a model adds what a viewer needs to open it."""

    tau: float | None = None
    decomposition: Decomposition | None = None
    histogram: Histogram | None = None
    levels: list[Level] | None = None
    dt: float | None = None
    exposure: float | None = Field(None, description="the exposure the run trained with")
    blur: LearnedBlur | None = Field(None, description="what an 'as captured' render shows (`kgs_core.run.learned_blur`)")
    static_only: bool | None = None
    sh_degree: int | None = None
    frames: list[FrameInfo] | None = None
    frame_rate: float | None = Field(None, description="frames a second of the clip, when its scene recorded one")
    edits: Edits | None = None


# A row of the training log (`log.csv`): its columns as they are in that run (iteration,
# train_seconds, loss, psnr_heldout, ...), NaN sent as null.
LogRow = dict[str, float | None]


# ------------------------------------------------------------------ exports


class ExportSummary(JobRow):
    run_id: str
    format: str
    params: dict = Field(description="the export request as given")
    progress: StageProgress | None = Field(None, description="while it runs: the stage and how far it is")
