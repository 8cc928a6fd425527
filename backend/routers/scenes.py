"""Scenes: list, create (synthesize, ingest an uploaded video, upload a dataset zip), inspect, delete."""

from __future__ import annotations

import fnmatch
import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from pydantic import Field, model_validator

from kgs_core.data.synth.scenes import SCENES

from ..deps import get_or_404, jobs, workspace
from ..jobs import JobRunner
from ..registry import Workspace
from ..schemas import StrictRequest

router = APIRouter(prefix="/api/scenes", tags=["scenes"])
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm")
MAX_ZIP_FILES = 20000
# What each upload kind must declare. Not text/plain or a form type: those a foreign web page
# can POST without a CORS preflight.
UPLOAD_TYPES = {"zip": ("application/zip", "application/x-zip-compressed", "application/octet-stream"),
                "video": ("video/*", "application/octet-stream")}


MAX_SYNTH_PIXELS = 1 << 31  # e.g. 1024² x 2048 x 1, 512² x 512 x 16, the demo's 128² x 60 x 16 = 2^24


class SynthRequest(StrictRequest):
    source: Literal["synth"] = "synth"
    name: str = Field("sheet", description="built-in scene: " + ", ".join(sorted(SCENES)))
    size: int = Field(128, ge=16, le=1024)
    frames: int = Field(60, ge=2, le=2000)
    subframes: int = Field(16, ge=1, le=64)
    blur: Literal["none", "mild", "severe"] = "mild"

    @model_validator(mode="after")
    def bounded_work(self) -> "SynthRequest":
        # Each bound alone allows 1024² x 2000 x 64 rendered pixels: days of CPU.
        renders = self.size * self.size * self.frames * self.subframes
        if renders > MAX_SYNTH_PIXELS:
            raise ValueError(f"size² x frames x subframes is {renders:,}, above {MAX_SYNTH_PIXELS:,} "
                             "(lower one of them)")
        return self


def public(row: dict) -> dict:
    return {k: row[k] for k in ("id", "name", "source", "status", "error", "created")}


def scene_summary(path: Path) -> dict:
    from kgs_core.data.formats import load_scene

    scene = load_scene(path)
    return {"frames": len(scene.frames), "train_frames": len(scene.train_frames), "test_frames": len(scene.test_frames),
            "image_size": [scene.frames[0].camera.width, scene.frames[0].camera.height], "dt": scene.dt,
            "exposure": scene.exposure, "format": scene.source_format, "has_ground_truth": scene.has_ground_truth}


@router.get("")
def list_scenes(ws: Workspace = Depends(workspace)) -> list[dict]:
    return [public(r) for r in ws.list("scenes")]


@router.post("", status_code=202)
def create_scene(req: SynthRequest, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    if req.name not in SCENES:
        raise HTTPException(422, f"unknown synthetic scene {req.name!r}; one of {sorted(SCENES)}")
    from ..registry import new_id

    sid = new_id()
    out = ws.new_dir("scenes", sid)
    row = ws.insert("scenes", id=sid, name=req.name, path=str(out), source="synth", status="queued")
    jr.start("scenes", sid, "synth", {"name": req.name, "out": str(out), "size": req.size, "frames": req.frames,
                                       "subframes": req.subframes, "blur": req.blur})
    return public(ws.get("scenes", row["id"]))


@router.post("/upload", status_code=201)
async def upload_scene(request: Request, name: str = Query(..., min_length=1, max_length=80, pattern=r"^[\w.\- ]+$"),
                       kind: Literal["zip", "video"] = Query(...), ws: Workspace = Depends(workspace),
                       jr: JobRunner = Depends(jobs)) -> dict:
    """Raw request body: a dataset folder as .zip (Nerfies, D-NeRF or COLMAP layout) or a video
    (ingested with SfM as a job). Size-limited while streaming; nothing is kept on failure."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if not any(fnmatch.fnmatchcase(ctype, t) for t in UPLOAD_TYPES[kind]):
        raise HTTPException(415, f"kind={kind} uploads need Content-Type {' or '.join(UPLOAD_TYPES[kind])}, "
                                 f"got {ctype or 'none'!r}")
    limit = request.app.state.settings.max_upload_mb * 1024 * 1024
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise HTTPException(413, f"upload of {int(declared)} bytes exceeds the limit of {limit} bytes")
    from ..registry import new_id

    sid = new_id()
    tmp_dir = Path(tempfile.mkdtemp(dir=ws.root / "scenes", prefix=f".upload-{sid}-"))
    try:
        blob = tmp_dir / ("upload.zip" if kind == "zip" else "upload.video")
        size = 0
        with open(blob, "wb") as f:
            async for chunk in request.stream():
                size += len(chunk)
                if size > limit:
                    raise HTTPException(413, f"upload exceeds the limit of {limit} bytes")
                f.write(chunk)
        if size == 0:
            raise HTTPException(422, "empty upload")
        head = blob.read_bytes()[:16]
        out = ws.new_dir("scenes", sid)
        if kind == "zip":
            if not head.startswith(b"PK\x03\x04"):
                raise HTTPException(415, "kind=zip but the body is not a zip archive")
            root = _safe_extract(blob, tmp_dir / "x", limit * 4)
            try:
                summary = scene_summary(root)
            except ValueError as exc:
                raise HTTPException(422, f"the zip is not a readable dataset: {exc}") from None
            shutil.move(str(root), out)
            row = ws.insert("scenes", id=sid, name=name, path=str(out), source="upload", status="done")
            return {**public(row), **summary}
        # a video: sniff the container, then ingest as a job
        import av

        try:
            with av.open(str(blob)) as c:
                if not c.streams.video:
                    raise HTTPException(415, "the upload has no video stream")
        except HTTPException:
            raise
        except Exception as exc:
            raise HTTPException(415, f"kind=video but the body is not a readable video ({type(exc).__name__})") from None
        video = ws.root / "scenes" / f".{sid}.video"
        shutil.move(str(blob), video)
        row = ws.insert("scenes", id=sid, name=name, path=str(out), source="ingest", status="queued")
        jr.start("scenes", sid, "ingest", {"video": str(video), "out": str(out), "delete_video": True})
        return public(ws.get("scenes", row["id"]))
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


def _safe_extract(zip_path: Path, dest: Path, max_bytes: int) -> Path:
    """Extracts refusing absolute paths, `..`, links and zip bombs; returns the dataset root
    (the folder holding dataset.json, transforms_*.json or sparse/)."""
    try:
        zf = zipfile.ZipFile(zip_path)
    except zipfile.BadZipFile:
        raise HTTPException(415, "corrupt zip archive") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > MAX_ZIP_FILES:
            raise HTTPException(413, f"zip has {len(infos)} entries (limit {MAX_ZIP_FILES})")
        if sum(i.file_size for i in infos) > max_bytes:
            raise HTTPException(413, "zip expands beyond the upload limit")
        dest.mkdir(parents=True)
        for info in infos:
            p = Path(info.filename)
            if p.is_absolute() or ".." in p.parts or (info.external_attr >> 16) & 0o170000 == 0o120000:
                raise HTTPException(422, f"unsafe path in zip: {info.filename!r}")
        zf.extractall(dest)
    markers = ("dataset.json", "transforms_train.json", "sparse")
    for cand in [dest, *sorted(p for p in dest.rglob("*") if p.is_dir())]:
        if any((cand / m).exists() for m in markers):
            return cand
    raise HTTPException(422, "no dataset in the zip (expected dataset.json, transforms_train.json or sparse/)")


@router.get("/{scene_id}")
def get_scene(scene_id: str, ws: Workspace = Depends(workspace)) -> dict:
    row = get_or_404(ws, "scenes", scene_id)
    out = public(row)
    if row["status"] == "done":
        try:
            out.update(scene_summary(Path(row["path"])))
        except ValueError as exc:
            out["error"] = str(exc)
    return out


@router.delete("/{scene_id}", status_code=204)
def delete_scene(scene_id: str, ws: Workspace = Depends(workspace)) -> None:
    row = get_or_404(ws, "scenes", scene_id)
    if row["status"] in ("queued", "running"):
        raise HTTPException(409, "the scene is still being created")
    runs = ws.list("runs", scene_id=scene_id)
    if runs:  # their renders, input frames and fine-tuning read the scene
        raise HTTPException(409, f"{len(runs)} run(s) use this scene ({', '.join(r['id'] for r in runs[:5])}): "
                                 "delete them first")
    path = Path(row["path"])
    if path.is_relative_to(ws.root):  # never delete data the user registered from elsewhere
        shutil.rmtree(path, ignore_errors=True)
    (ws.root / "scenes" / f".{scene_id}.video").unlink(missing_ok=True)  # an upload whose ingest never ran
    ws.delete("scenes", scene_id)
