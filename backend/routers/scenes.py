"""Scenes: list, create (synthesize, upload and ingest videos, upload a dataset zip), inspect, cancel, delete."""

from __future__ import annotations

import fnmatch
import json
import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path
from typing import Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool

from kgs_core.job_options import IngestOptions, SynthOptions

from ..deps import get_or_404, jobs, workspace
from ..jobs import JobRunner
from ..registry import ACTIVE, JobStatus, Workspace, relative_text
from ..responses import SceneDetail, SceneSummary

router = APIRouter(prefix="/api/scenes", tags=["scenes"])
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm")
MAX_ZIP_FILES = 20000
# What each upload kind must declare. Not text/plain or a form type: those a foreign web page
# can POST without a CORS preflight.
UPLOAD_TYPES = {
    "zip": ("application/zip", "application/x-zip-compressed", "application/octet-stream"),
    "video": ("video/*", "application/octet-stream"),
}


class SynthRequest(SynthOptions):
    __doc__ = SynthOptions.__doc__  # `kgs_core.job_options`: the options `kgs-app synth` takes

    source: Literal["synth"] = "synth"


# Scene states from which an uploaded video can be ingested (again).
INGESTABLE = (JobStatus.UPLOADED, JobStatus.FAILED, JobStatus.CANCELLED, JobStatus.INTERRUPTED)


def public(row: dict, ws: Workspace) -> dict:
    out = {k: row[k] for k in ("id", "name", "source", "status", "error", "created", "queue_position")}
    if row["source"] == "ingest":
        out["videos"] = sum(video_path(ws, row["id"], r).is_file() for r in ("video", "sharp"))
        try:  # the ingest's stages: the current one, and those done with their seconds (worker.stage_writer)
            out["progress"] = json.loads(progress_path(ws, row["id"]).read_text())
        except (OSError, ValueError):
            out["progress"] = None
    return out


def scene_summary(path: Path, scene=None) -> dict:
    from kgs_core.data.formats import load_scene

    scene = scene or load_scene(path)
    return {
        "frames": len(scene.frames),
        "train_frames": len(scene.train_frames),
        "test_frames": len(scene.test_frames),
        "image_size": [scene.frames[0].camera.width, scene.frames[0].camera.height],
        "dt": scene.dt,
        "exposure": scene.exposure,
        "format": scene.source_format,
        "has_ground_truth": scene.has_ground_truth,
    }


@router.get("", response_model=list[SceneSummary])
def list_scenes(ws: Workspace = Depends(workspace)) -> list[dict]:
    return [public(r, ws) for r in ws.list("scenes")]


@router.post("", status_code=202, response_model=SceneSummary)
def create_scene(req: SynthRequest, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    from ..registry import new_id

    sid = new_id()
    out = ws.new_dir("scenes", sid)
    row = ws.insert("scenes", id=sid, name=req.name, path=str(out), source="synth", status=JobStatus.QUEUED)
    jr.start("scenes", sid, "synth", {"out": str(out), **req.model_dump(exclude={"source"})})
    return public(ws.get("scenes", row["id"]), ws)


# How an uploaded video becomes a scene: `kgs_core.job_options.IngestOptions`, as `kgs-app ingest` takes them.
IngestRequest = IngestOptions


def video_path(ws: Workspace, scene_id: str, role: str = "video") -> Path:
    """Where an uploaded video waits for its ingest (outside the scene folder, which ingest replaces)."""
    return ws.root / "scenes" / (f".{scene_id}.video" if role == "video" else f".{scene_id}.{role}.video")


def progress_path(ws: Workspace, scene_id: str) -> Path:
    return ws.root / "jobs" / f"{scene_id}.progress.json"


async def receive_upload(request: Request, kind: str, tmp_dir: Path) -> Path:
    """The raw request body, streamed into `tmp_dir` under the upload limit, with the declared
    Content-Type checked against `kind` first."""
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if not any(fnmatch.fnmatchcase(ctype, t) for t in UPLOAD_TYPES[kind]):
        raise HTTPException(415, f"kind={kind} uploads need Content-Type {' or '.join(UPLOAD_TYPES[kind])}, got {ctype or 'none'!r}")
    limit = request.app.state.settings.max_upload_mb * 1024 * 1024
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise HTTPException(413, f"upload of {int(declared)} bytes exceeds the limit of {limit} bytes")
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
    return blob


def check_video(blob: Path) -> None:
    """415 unless PyAV opens `blob` and finds a video stream in it."""
    import av

    try:
        with av.open(str(blob)) as c:
            if not c.streams.video:
                raise HTTPException(415, "the upload has no video stream")
    except HTTPException:
        raise
    except Exception as exc:
        raise HTTPException(415, f"kind=video but the body is not a readable video ({type(exc).__name__})") from None


def start_ingest(ws: Workspace, jr: JobRunner, row: dict, req: IngestRequest) -> None:
    sharp = video_path(ws, row["id"], "sharp")
    # One of two racing requests claims the scene; the other gets a 409.
    if not ws.transition("scenes", row["id"], INGESTABLE, status=JobStatus.QUEUED, error=None):
        raise HTTPException(409, f"scene {row['id']} is already being ingested")
    progress_path(ws, row["id"]).unlink(missing_ok=True)
    jr.start(
        "scenes",
        row["id"],
        "ingest",
        {
            "video": str(video_path(ws, row["id"])),
            "eval_video": str(sharp) if sharp.is_file() else None,
            "out": row["path"],
            "delete_video": True,
            "progress": str(progress_path(ws, row["id"])),
            **req.model_dump(exclude_none=True),
        },
    )


@router.post("/upload", status_code=201, response_model=SceneDetail)
async def upload_scene(
    request: Request,
    name: str = Query(..., min_length=1, max_length=80, pattern=r"^[\w.\- ]+$"),
    kind: Literal["zip", "video"] = Query(...),
    hold: bool = Query(
        False, description="video: keep it as 'uploaded' (a second camera's video may follow) until POST /api/scenes/{id}/ingest"
    ),
    ws: Workspace = Depends(workspace),
    jr: JobRunner = Depends(jobs),
) -> dict:
    """Raw request body: a dataset folder as .zip (Nerfies, D-NeRF or COLMAP layout) or a video
    (ingested with SfM as a job, at once with the default options, or when asked with `hold`).
    Size-limited while streaming; nothing is kept on failure."""
    from ..registry import new_id

    sid = new_id()
    tmp_dir = Path(tempfile.mkdtemp(dir=ws.root / "scenes", prefix=f".upload-{sid}-"))
    try:
        blob = await receive_upload(request, kind, tmp_dir)
        if kind == "zip":
            with open(blob, "rb") as f:  # the magic bytes only: the body can be hundreds of MB
                if f.read(4) != b"PK\x03\x04":
                    raise HTTPException(415, "kind=zip but the body is not a zip archive")
            limit = request.app.state.settings.max_upload_mb * 1024 * 1024 * 4
            summary, root = await run_in_threadpool(read_uploaded_dataset, blob, tmp_dir / "x", limit)
            out = ws.new_dir("scenes", sid)
            shutil.move(str(root), out)
            row = ws.insert("scenes", id=sid, name=name, path=str(out), source="upload", status=JobStatus.DONE)
            return {**public(row, ws), **summary}
        await run_in_threadpool(check_video, blob)
        out = ws.new_dir("scenes", sid)
        shutil.move(str(blob), video_path(ws, sid))
        row = ws.insert("scenes", id=sid, name=name, path=str(out), source="ingest", status=JobStatus.UPLOADED)
        if not hold:
            start_ingest(ws, jr, row, IngestRequest())
        return public(ws.get("scenes", sid), ws)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)


def read_uploaded_dataset(blob: Path, dest: Path, max_bytes: int) -> tuple[dict, Path]:
    """The summary and root folder of a dataset zip, extracted into `dest`; 4xx when it is not
    a readable dataset or a frame holds more pixels than a frame may. Errors name files
    relative to the dataset, never the server's folders."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.formats.common import image_size  # (from the header, nothing decoded)
    from kgs_core.data.images import MAX_IMAGE_PIXELS

    root = _safe_extract(blob, dest, max_bytes)
    try:
        scene = load_scene(root)
        for frame in scene.frames:
            for path in (frame.image_path, frame.sharp_path, frame.mask_path):
                if path is not None and path.suffix.lower() != ".npy":
                    w, h = image_size(path)
                    if w * h > MAX_IMAGE_PIXELS:
                        raise HTTPException(
                            413, f"{path.relative_to(root.resolve())} is {w}x{h}, above the {MAX_IMAGE_PIXELS:,} pixels a frame may hold"
                        )
        summary = scene_summary(root, scene)
    except ValueError as exc:
        raise HTTPException(422, "the zip is not a readable dataset: " + relative_text(str(exc), root)) from None
    return summary, root


def waiting_video(ws: Workspace, scene_id: str) -> dict:
    """The row of a scene whose uploaded video can be (re-)ingested: 409 otherwise."""
    row = get_or_404(ws, "scenes", scene_id)
    if row["source"] != "ingest" or row["status"] not in INGESTABLE or not video_path(ws, scene_id).is_file():
        raise HTTPException(409, f"scene {scene_id} has no uploaded video waiting for ingest (status: {row['status']})")
    return row


@router.post("/{scene_id}/video", status_code=201, response_model=SceneSummary)
async def upload_second_video(
    scene_id: str, request: Request, role: Literal["sharp"] = Query(...), ws: Workspace = Depends(workspace)
) -> dict:
    """A second camera's video of the same moment (raw body), synchronised with the first and with
    as many frames: ingest poses both, trains on the first, and keeps the second for evaluation."""
    waiting_video(ws, scene_id)
    tmp_dir = Path(tempfile.mkdtemp(dir=ws.root / "scenes", prefix=f".upload-{scene_id}-"))
    try:
        blob = await receive_upload(request, "video", tmp_dir)
        check_video(blob)
        shutil.move(str(blob), video_path(ws, scene_id, role))
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)
    return public(ws.get("scenes", scene_id), ws)


@router.post("/{scene_id}/ingest", status_code=202, response_model=SceneSummary)
def ingest_scene(scene_id: str, req: IngestRequest, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    """Starts (or, after a failure or a cancel, retries) the ingest of an uploaded video."""
    start_ingest(ws, jr, waiting_video(ws, scene_id), req)
    return public(ws.get("scenes", scene_id), ws)


@router.post("/{scene_id}/cancel", status_code=202, response_model=SceneSummary)
def cancel_scene(scene_id: str, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    """Stops a scene's job (an ingest or a synthesis); its uploaded video stays for a retry."""
    get_or_404(ws, "scenes", scene_id)
    if not jr.cancel("scenes", scene_id):
        raise HTTPException(409, f"scene {scene_id} has no job running")
    return public(ws.get("scenes", scene_id), ws)


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
        try:  # each entry's data is checked against its header (sizes, CRC) as it is read
            zf.extractall(dest)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, NotImplementedError, ValueError) as exc:
            raise HTTPException(415, f"corrupt zip archive ({type(exc).__name__}: {exc})") from None
    markers = ("dataset.json", "transforms_train.json", "sparse")
    for cand in [dest, *sorted(p for p in dest.rglob("*") if p.is_dir())]:
        if any((cand / m).exists() for m in markers):
            return cand
    raise HTTPException(422, "no dataset in the zip (expected dataset.json, transforms_train.json or sparse/)")


@router.get("/{scene_id}", response_model=SceneDetail)
def get_scene(scene_id: str, ws: Workspace = Depends(workspace)) -> dict:
    row = get_or_404(ws, "scenes", scene_id)
    out = public(row, ws)
    if row["status"] == JobStatus.DONE:
        try:
            out.update(scene_summary(Path(row["path"])))
        except ValueError as exc:
            out["error"] = relative_text(str(exc), ws.root)
    return out


@router.delete("/{scene_id}", status_code=204)
def delete_scene(scene_id: str, ws: Workspace = Depends(workspace)) -> None:
    row = get_or_404(ws, "scenes", scene_id)
    if row["status"] in ACTIVE:
        raise HTTPException(409, "the scene is still being created (cancel it first)")
    runs = ws.list("runs", scene_id=scene_id)
    if runs:  # their renders, input frames and fine-tuning read the scene
        raise HTTPException(409, f"{len(runs)} run(s) use this scene ({', '.join(r['id'] for r in runs[:5])}): delete them first")
    # Never data the user registered from elsewhere (`remove` touches files inside the workspace only).
    ws.remove(
        [("scenes", scene_id)],
        [Path(row["path"]), *(video_path(ws, scene_id, role) for role in ("video", "sharp")), progress_path(ws, scene_id)],
    )
