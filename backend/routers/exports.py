"""Exports as jobs: start one for a run, poll it, download the result (a folder comes zipped)."""

from __future__ import annotations

import json
import re
import shutil
import threading
import uuid
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import FileResponse

from kgs_core.export import SUFFIX
from kgs_core.job_options import ExportOptions

from ..deps import get_or_404, jobs, workspace
from ..jobs import JobRunner
from ..registry import ACTIVE, JobStatus, Workspace, new_id
from ..responses import ExportSummary

router = APIRouter(tags=["exports"])


# The body: `kgs_core.job_options.ExportOptions`, as `kgs-app export` takes them.
ExportRequest = ExportOptions


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
def start_export(run_id: str, req: ExportRequest, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    run = get_or_404(ws, "runs", run_id)
    if not (Path(run["path"]) / "model.pt").is_file():
        raise HTTPException(409, f"run {run_id} has no model yet (status: {run['status']})")
    eid = new_id()
    out = ws.new_dir("exports", eid) / (f"{req.format}{SUFFIX.get(req.format, '')}")
    ws.insert("exports", id=eid, run_id=run_id, format=req.format, path=str(out), status=JobStatus.QUEUED, params=req.model_dump())
    jr.start(
        "exports", eid, "export", {"run_dir": run["path"], "out": str(out), **req.model_dump(), "progress": str(progress_path(ws, eid))}
    )
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
