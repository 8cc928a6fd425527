"""Exports as jobs: start one for a run, poll it, download the result (a folder comes zipped)."""

from __future__ import annotations

import json
import re
import shutil
import threading
import uuid
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from kgs_core.export import SUFFIX
from kgs_core.export.bake import parse_times
from kgs_core.export.camera_path import view_path

from ..deps import get_or_404, jobs, workspace
from ..jobs import JobRunner
from ..registry import ACTIVE, JobStatus, Workspace, new_id
from ..responses import ExportSummary
from ..schemas import StrictRequest

router = APIRouter(tags=["exports"])


class ViewCamera(BaseModel):
    """The viewer's current view, for a video from where the user looks."""

    model_config = ConfigDict(extra="forbid")
    viewmat: list[list[float]] = Field(description="4x4 world-to-camera (OpenCV axes), row-major")
    fov_deg: float = Field(ge=1, lt=179, description="horizontal field of view")
    width: int = Field(ge=16, le=4096)
    height: int = Field(ge=16, le=4096)


class ExportRequest(StrictRequest):
    format: Literal["ply-seq", "splat", "splatv", "mp4", "glb"]
    times: str | None = Field(None, max_length=10000, description="T, T1,T2,... or START:STOP:COUNT")
    camera_path: Literal["training", "orbit", "view"] = Field("training", description="mp4: the training cameras, "
                                                             "an orbit, or `view` (one fixed camera)")
    view: ViewCamera | None = Field(None, description="the camera of camera_path `view`")
    exposure: float = Field(0.0, ge=0, le=1)
    lod: int | None = Field(None, ge=1)
    side_by_side: bool = Field(False, description="mp4 on the training path: the input frame beside each render")
    size: int | None = Field(None, ge=16, le=4096, description="mp4: the video's long side in pixels")
    fps: float = Field(24.0, gt=0, le=240, description="mp4: frames a second")
    web_frame: bool | None = Field(None, description="write the file at the web viewers' default view (default: on "
                                   "for splat and splatv)")

    @field_validator("times")
    @classmethod
    def times_parse(cls, v: str | None) -> str | None:
        """Refused here (422), not by the export job after a 202."""
        parse_times(v, [])
        return v

    @model_validator(mode="after")
    def options_fit_the_format(self) -> "ExportRequest":
        """The combinations `export_run` refuses, refused before the job starts."""
        if (self.camera_path == "view") != (self.view is not None):
            raise ValueError("camera_path 'view' and a view go together")
        if self.view is not None:
            view_path(self.view.model_dump(), [0.0])  # a viewmat that is not a rotation
        if self.side_by_side and self.camera_path != "training":
            raise ValueError("side_by_side needs camera_path 'training'")
        if self.size is not None and self.format != "mp4":
            raise ValueError("size sets a video's resolution: only with format mp4")
        if self.web_frame and self.format not in ("ply-seq", "splat", "splatv"):
            raise ValueError(f"web_frame is for ply-seq, splat and splatv, not {self.format}")
        if self.format == "glb" and len(parse_times(self.times, [0.5])) != 1:
            raise ValueError("glb exports one time")
        return self


def public(row: dict, ws: Workspace | None = None) -> dict:
    out = {k: row[k] for k in ("id", "run_id", "format", "status", "error", "created", "params", "queue_position")}
    if ws is not None and row["status"] == JobStatus.RUNNING:
        try:
            out["progress"] = json.loads(progress_path(ws, row["id"]).read_text())
        except (OSError, ValueError):
            out["progress"] = None
    return out


def progress_path(ws: Workspace, export_id: str) -> Path:
    return ws.root / "jobs" / f"{export_id}.progress.json"


@router.post("/api/runs/{run_id}/exports", status_code=202, response_model=ExportSummary)
def start_export(run_id: str, req: ExportRequest, ws: Workspace = Depends(workspace),
                 jr: JobRunner = Depends(jobs)) -> dict:
    run = get_or_404(ws, "runs", run_id)
    if not (Path(run["path"]) / "model.pt").is_file():
        raise HTTPException(409, f"run {run_id} has no model yet (status: {run['status']})")
    eid = new_id()
    out = ws.new_dir("exports", eid) / (f"{req.format}{SUFFIX.get(req.format, '')}")
    ws.insert("exports", id=eid, run_id=run_id, format=req.format, path=str(out), status=JobStatus.QUEUED,
              params=req.model_dump())
    jr.start("exports", eid, "export", {"run_dir": run["path"], "out": str(out), **req.model_dump(),
                                        "progress": str(progress_path(ws, eid))})
    return public(ws.get("exports", eid))


@router.get("/api/runs/{run_id}/exports", response_model=list[ExportSummary])
def list_exports(run_id: str, ws: Workspace = Depends(workspace)) -> list[dict]:
    get_or_404(ws, "runs", run_id)
    return [public(r) for r in ws.list("exports", run_id=run_id)]


@router.get("/api/exports/{export_id}", response_model=ExportSummary)
def get_export(export_id: str, ws: Workspace = Depends(workspace)) -> dict:
    return public(get_or_404(ws, "exports", export_id), ws)


@router.get("/api/exports/{export_id}/download")
def download(export_id: str, ws: Workspace = Depends(workspace)) -> FileResponse:
    row = get_or_404(ws, "exports", export_id)
    if row["status"] != JobStatus.DONE:
        raise HTTPException(409, f"export {export_id} is {row['status']}")
    path = Path(row["path"])
    if path.is_dir():
        path = zipped(path)
    if not path.is_file():
        raise HTTPException(410, "the export's files are gone")
    run = ws.get("runs", row["run_id"])
    # Named after the run, as the user named it (letters, digits, dot, dash and underscore kept).
    stem = re.sub(r"[^\w.\-]+", "_", run["name"]).strip("._") if run else ""
    return FileResponse(path, filename=f"{stem or row['run_id']}-{path.name}", media_type="application/octet-stream")


_zip_lock = threading.Lock()


def zipped(folder: Path) -> Path:
    """`folder.zip`, built once: concurrent first downloads wait for the one that builds it
    (each used to write the same temporary file, and all but one failed), and it appears under
    its final name only when complete (a unique temporary name, then a rename)."""
    archive = folder.with_suffix(".zip")
    with _zip_lock:
        if not archive.is_file():
            base = folder.parent / f".{folder.name}.{uuid.uuid4().hex}"
            try:
                Path(shutil.make_archive(str(base), "zip", root_dir=folder)).replace(archive)
            finally:
                Path(f"{base}.zip").unlink(missing_ok=True)
    return archive


@router.delete("/api/exports/{export_id}", status_code=204)
def delete_export(export_id: str, ws: Workspace = Depends(workspace)) -> None:
    row = get_or_404(ws, "exports", export_id)
    if row["status"] in ACTIVE:
        raise HTTPException(409, "the export is still running")
    ws.remove([("exports", export_id)], [Path(row["path"]).parent])
    progress_path(ws, export_id).unlink(missing_ok=True)
