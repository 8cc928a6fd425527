"""Runs: list, start training, status and metadata, cancel, delete, live τ, edits, training log."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Request
from pydantic import Field

from kgs_core.job_options import TrainOptions
from kgs_core.run import RunError, learned_blur, read_log
from kgs_core.train.config import TrainConfig, make_config

from ..deps import get_or_404, jobs, run_view, workspace
from ..jobs import JobRunner, last_checkpoint
from ..registry import ACTIVE, JobStatus, Workspace, new_id
from ..responses import Decomposition, Edits, LogRow, ObjectSelection, RunDetail, RunSummary
from ..schemas import StrictRequest

router = APIRouter(prefix="/api/runs", tags=["runs"])


class TrainRequest(TrainOptions):  # type: ignore[valid-type,misc]
    """`kgs_core.job_options.TrainOptions`, as `kgs-app train` takes them, and what the server
    adds: the scene by id, a name, and a finished run to start from (by id: never a path)."""

    scene_id: str
    name: str | None = Field(None, max_length=80)
    init_from_run: str | None = Field(
        None, pattern=r"^[0-9a-f]{12}$", description="the id of a finished run whose model this one starts from (fine-tuning)"
    )


class TauRequest(StrictRequest):
    tau: float = Field(..., gt=0, description="dynamic when the temporal variance K exceeds tau")


class FinetuneRequest(StrictRequest):
    tau: float | None = Field(None, gt=0, description="decomposition threshold (default: the viewer's live τ)")
    iterations: int = Field(300, ge=1, le=100_000)


class EditRequest(StrictRequest):
    op: Literal["delete", "hide", "unhide", "restore", "crop", "clear", "undo", "redo"]
    lod: int | None = None
    indices: list[int] = Field([], max_length=5_000_000)
    crop: dict | None = None


class ObjectRequest(StrictRequest):
    index: int = Field(ge=0, description="a dynamic Gaussian of the object (its index within the LoD level)")
    t: float = Field(ge=0, le=1, description="the time the object is looked at")
    lod: int | None = None


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}


def saved_config(run_id: str, info: dict) -> TrainConfig:
    """The configuration a run's run.json records, or a 409 naming what is wrong with it."""
    try:
        return TrainConfig.from_dict(info.get("config"))
    except ValueError as exc:
        raise HTTPException(409, f"run {run_id}: run.json: {exc}") from None


def public(row: dict) -> dict:
    path = Path(row["path"])
    info = read_json(path / "run.json")
    out = {k: row[k] for k in ("id", "scene_id", "name", "status", "error", "created", "queue_position")}
    # What tells two runs of one name apart on the runs page: their scene and their folder
    # (its last two parts: the server's own layout is not the client's business).
    out["scene_name"] = info.get("scene_name")
    out["folder"] = f"{path.parent.name}/{path.name}"
    out["progress"] = read_json(path / "progress.json") or None
    out["has_model"] = (path / "model.pt").is_file()
    for k in ("iteration", "train_seconds", "final_psnr_heldout", "gaussians", "dynamic_share", "lod_levels"):
        if k in info:
            out[k] = info[k]
    out["resumable"] = resumable(row, info)
    return out


def resumable(row: dict, info: dict) -> bool:
    """A run that stopped short of its iterations (interrupted, cancelled or failed) and left
    a checkpoint to continue from."""
    last = last_checkpoint(Path(row["path"]))
    total = (info.get("config") or {}).get("iterations")
    return (
        row["status"] in (JobStatus.INTERRUPTED, JobStatus.CANCELLED, JobStatus.FAILED)
        and last is not None
        and isinstance(total, int)
        and last < total
    )


@router.get("", response_model=list[RunSummary])
def list_runs(ws: Workspace = Depends(workspace)) -> list[dict]:
    return [public(r) for r in ws.list("runs")]


@router.post("", status_code=202, response_model=RunSummary)
def start_run(req: TrainRequest, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    scene = get_or_404(ws, "scenes", req.scene_id)
    if scene["status"] != JobStatus.DONE:
        raise HTTPException(409, f"scene {req.scene_id} is not ready (status: {scene['status']})")
    overrides = req.overrides()
    try:
        make_config(req.preset, ablate=tuple(req.ablate), **overrides)  # refused here, not in the job
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    parent = None
    if req.init_from_run is not None:  # a run of this workspace, by id: a request never names a path
        parent = get_or_404(ws, "runs", req.init_from_run)
        if not (Path(parent["path"]) / "model.pt").is_file():
            raise HTTPException(409, f"run {req.init_from_run} has no model to start from (status: {parent['status']})")
    rid = new_id()
    run_dir = ws.new_dir("runs", rid)
    row = ws.insert(
        "runs",
        id=rid,
        scene_id=scene["id"],
        name=req.name or f"{scene['name']}-{req.preset}",
        path=str(run_dir),
        status=JobStatus.QUEUED,
        params=req.model_dump(),
    )
    jr.start(
        "runs",
        rid,
        "train",
        {
            "scene_dir": scene["path"],
            "run_dir": str(run_dir),
            "preset": req.preset,
            "ablate": req.ablate,
            "overrides": overrides,
            "init_from": parent["path"] if parent else None,
        },
    )
    return public(ws.get("runs", row["id"]))


@router.get("/{run_id}", response_model=RunDetail)
def get_run(run_id: str, request: Request, ws: Workspace = Depends(workspace)) -> dict:
    """Status, and for a trained run: frames (time, camera), τ, K histogram, LoD levels, counts."""
    row = get_or_404(ws, "runs", run_id)
    out = public(row)
    if not out["has_model"]:
        return out
    view = run_view(request.app, run_id)
    out["tau"] = view.tau
    out["decomposition"] = view.decomposition()
    out["histogram"] = view.histogram()
    out["lod_levels"] = view.run.n_levels
    out["levels"] = [{"level": lvl, "gaussians": len(view.run.level(lvl))} for lvl in range(1, view.run.n_levels + 1)]
    out["dt"] = view.dt
    out["exposure"] = view.run.info.get("exposure", 0.0)
    out["blur"] = learned_blur(view.run.info)
    out["static_only"] = view.run.static_only
    out["sh_degree"] = view.run.model.config.sh_degree
    out["frames"] = view.frames()
    out["frame_rate"] = view.frame_rate
    out["edits"] = view.edits.to_dict()
    return out


@router.get("/{run_id}/log", response_model=list[LogRow])
def get_log(run_id: str, ws: Workspace = Depends(workspace)) -> list[dict]:
    row = get_or_404(ws, "runs", run_id)
    rows = read_log(Path(row["path"]))
    return [{k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()} for r in rows]


@router.post("/{run_id}/cancel", response_model=RunSummary)
def cancel_run(run_id: str, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    get_or_404(ws, "runs", run_id)
    if not jr.cancel("runs", run_id):
        raise HTTPException(409, "the run is not training")
    return public(ws.get("runs", run_id))


@router.post("/{run_id}/resume", status_code=202, response_model=RunSummary)
def resume_run(run_id: str, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    """Continues a run that stopped short from its last checkpoint, with its own configuration."""
    row = get_or_404(ws, "runs", run_id)
    info = read_json(Path(row["path"]) / "run.json")
    if not resumable(row, info):
        raise HTTPException(409, f"run {run_id} cannot be resumed (status: {row['status']}; it needs a checkpoint short of its iterations)")
    scene = ws.get("scenes", row["scene_id"]) if row["scene_id"] else None
    if scene is None:
        raise HTTPException(409, "the run's scene is no longer in the workspace")
    saved_config(run_id, info)  # a malformed run.json is refused here, not in the job
    if not ws.transition("runs", run_id, (row["status"],), status=JobStatus.QUEUED, error=None):
        raise HTTPException(409, f"run {run_id} is already being resumed")
    jr.start("runs", run_id, "train", {"scene_dir": scene["path"], "run_dir": row["path"], "config": info["config"], "resume": True})
    return public(ws.get("runs", run_id))


@router.delete("/{run_id}", status_code=204)
def delete_run(run_id: str, request: Request, ws: Workspace = Depends(workspace)) -> None:
    row = get_or_404(ws, "runs", run_id)
    if row["status"] in ACTIVE:
        raise HTTPException(409, "the run is training: cancel it first")
    exports = ws.list("exports", run_id=run_id)
    if any(e["status"] in ACTIVE for e in exports):
        raise HTTPException(409, "an export of this run is running: wait for it or cancel it first")
    request.app.state.views.drop(run_id)
    # Its exports go with it: a deleted run's files must not stay downloadable.
    folders = [Path(e["path"]).parent for e in exports if Path(e["path"]).parent.is_relative_to(ws.root / "exports")]
    ws.remove([*(("exports", e["id"]) for e in exports), ("runs", run_id)], [*folders, Path(row["path"])])


@router.post("/{run_id}/tau", response_model=Decomposition)
async def set_tau(run_id: str, req: TauRequest, request: Request) -> dict:
    """Recomputes the static/dynamic decomposition from the stored K (no retraining) and pushes the new
    sets to every viewer subscribed to the run."""
    view = run_view(request.app, run_id)
    decomposition = view.set_tau(req.tau)
    await request.app.state.hub.broadcast(run_id, {"type": "decomposition", **decomposition})
    return decomposition


@router.post("/{run_id}/finetune", status_code=202, response_model=RunSummary)
def finetune(
    run_id: str, req: FinetuneRequest, request: Request, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)
) -> dict:
    """A new run that continues this one's model with the decomposition at `tau` (the live τ when not
    given): the decomposition chosen in the viewer, then trained further."""
    from kgs_core.train.config import finetune_config

    parent = get_or_404(ws, "runs", run_id)
    path = Path(parent["path"])
    if not (path / "model.pt").is_file():
        raise HTTPException(409, f"run {run_id} has no model to fine-tune (status: {parent['status']})")
    info = read_json(path / "run.json")
    tau = req.tau if req.tau is not None else run_view(request.app, run_id).tau
    cfg = finetune_config(saved_config(run_id, info), req.iterations, tau)
    cfg.init_from = str(path)
    rid = new_id()
    run_dir = ws.new_dir("runs", rid)
    scene = ws.get("scenes", parent["scene_id"]) if parent["scene_id"] else None
    if scene:
        scene_dir = scene["path"]
    else:
        try:
            scene_dir = str(run_view(request.app, run_id).run.scene_path())
        except RunError:
            raise HTTPException(409, f"run {run_id}: its scene is no longer there") from None
    ws.insert(
        "runs",
        id=rid,
        scene_id=parent["scene_id"],
        name=f"{parent['name']}-ft",
        path=str(run_dir),
        status=JobStatus.QUEUED,
        params={"finetune_of": run_id, "tau": tau, "iterations": req.iterations},
    )
    jr.start("runs", rid, "train", {"scene_dir": scene_dir, "run_dir": str(run_dir), "config": cfg.to_dict()})
    return public(ws.get("runs", rid))


@router.get("/{run_id}/edits", response_model=Edits)
def get_edits(run_id: str, request: Request) -> dict:
    return run_view(request.app, run_id).edits.to_dict()


@router.post("/{run_id}/edits", response_model=Decomposition)
async def edit(run_id: str, req: EditRequest, request: Request) -> dict:
    view = run_view(request.app, run_id)
    try:
        decomposition = view.apply_edit(req.op, req.lod, req.indices, req.crop)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    await request.app.state.hub.broadcast(run_id, {"type": "decomposition", **decomposition})
    return decomposition


@router.post("/{run_id}/select-object", response_model=ObjectSelection)
def select_object(run_id: str, req: ObjectRequest, request: Request) -> dict:
    """The moving object a Gaussian belongs to: the kept dynamic Gaussians connected to it at
    time t (`kgs_core.selection`)."""
    try:
        return run_view(request.app, run_id).object_at(req.index, req.t, req.lod)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
