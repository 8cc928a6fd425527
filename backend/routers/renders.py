"""Server-side renders with the CPU rasteriser: PNG/JPEG of a run at a camera, time, exposure,
LoD and set (all, static, dynamic); input frames for side-by-side comparison."""

from __future__ import annotations

import io
from dataclasses import replace
from typing import Literal

import numpy as np
from fastapi import APIRouter, HTTPException, Query, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from kgs_core.data.scene import Camera

from ..deps import run_view

router = APIRouter(prefix="/api/runs", tags=["renders"])
# The most pixels one render may ask for (width x height): a 2048 x 2048 render on two cores takes
# seconds; larger ones held the server's threads for most of a minute.
MAX_RENDER_PIXELS = 2048 * 2048


def scene_frames(view) -> list:
    """The frames of a run's scene, or a 409 when the scene cannot be read (moved, deleted or
    malformed)."""
    from kgs_core.data.formats import load_scene

    try:
        return load_scene(view.run.scene_path()).frames
    except ValueError as exc:
        raise HTTPException(409, f"the run's scene is not available: {exc}") from None


def _encode(img: np.ndarray, fmt: str) -> tuple[bytes, str]:
    from PIL import Image

    buf = io.BytesIO()
    im = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    if fmt == "png":
        im.save(buf, format="PNG")
    else:
        im.save(buf, format="JPEG", quality=90)
    return buf.getvalue(), f"image/{fmt}"


def camera_for(view, frame: int | None, viewmat: str | None, width: int | None, height: int | None, fx: float | None) -> Camera:
    frames = scene_frames(view)
    base = frames[min(frame or 0, len(frames) - 1)].camera
    if frame is not None and not 0 <= frame < len(frames):
        raise HTTPException(422, f"frame must be in 0..{len(frames) - 1}")
    cam = base
    if viewmat is not None:
        try:
            vm = np.array([float(v) for v in viewmat.split(",")], dtype=np.float64).reshape(4, 4)
        except ValueError:
            raise HTTPException(422, "viewmat: 16 comma-separated numbers (row-major world-to-camera)") from None
        R = vm[:3, :3]
        if not (np.isfinite(vm).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-3)):
            raise HTTPException(422, "viewmat: the rotation part is not a rotation")
        cam = replace(cam, viewmat=vm)
    if width or height:
        w, h = width or cam.width, height or cam.height
        K = cam.K.copy()
        K[0] *= w / cam.width
        K[1] *= h / cam.height
        cam = replace(cam, K=K, width=w, height=h)
    if fx:
        K = cam.K.copy()
        K[0, 0] = K[1, 1] = fx
        cam = replace(cam, K=K)
    if cam.width * cam.height > MAX_RENDER_PIXELS:
        raise HTTPException(
            422,
            f"a render of {cam.width}x{cam.height} is above the {MAX_RENDER_PIXELS:,} pixels one "
            "render may have: ask for a smaller width and height",
        )
    return cam


@router.get("/{run_id}/render", responses={200: {"content": {"image/png": {}, "image/jpeg": {}}}})
async def render(
    request: Request,
    run_id: str,
    t: float = Query(0.0, ge=0, le=1),
    exposure: float = Query(0.0, ge=0, le=1),
    lod: int | None = Query(None, ge=1),
    set: Literal["all", "static", "dynamic"] = "all",
    frame: int | None = Query(None, ge=0, description="the camera of this scene frame (default 0)"),
    viewmat: str | None = Query(None, description="16 numbers, row-major world-to-camera"),
    width: int | None = Query(None, ge=8, le=4096, description="width x height at most 2048²"),
    height: int | None = Query(None, ge=8, le=4096),
    fx: float | None = Query(None, gt=0),
    format: Literal["png", "jpeg"] = "png",
    background: Literal["black", "white"] = "black",
) -> Response:
    view = run_view(request.app, run_id)
    if lod is not None and lod > view.run.n_levels:
        raise HTTPException(422, f"lod must be in 1..{view.run.n_levels}")
    cam = await run_in_threadpool(camera_for, view, frame, viewmat, width, height, fx)  # reads the scene

    def work():
        from kgs_core.export.bake import render_baked

        g, _ = view.baked(t, exposure, lod, set)
        bg = np.ones(3) if background == "white" else np.zeros(3)
        return render_baked(g, cam, view.run.model.config.sh_degree, bg).image.numpy()

    data, media = _encode(await run_in_threadpool(work), format)
    return Response(data, media_type=media, headers={"Cache-Control": "no-store"})


THUMBNAIL_SIDE = 160  # the long side of a runs-page thumbnail, in pixels


@router.get("/{run_id}/thumbnail", responses={200: {"content": {"image/jpeg": {}}}})
async def thumbnail(request: Request, run_id: str) -> Response:
    """A small JPEG of the run at mid-clip from its first training camera, edits applied; kept
    beside the model (`RUN/.thumbnail.jpg`) until the model or the edits change."""
    view = run_view(request.app, run_id)
    run_dir = view.run.path

    def work() -> bytes:
        from kgs_core.export.bake import render_baked
        from kgs_core.io import atomic_write_bytes

        stamps = [p.stat().st_mtime_ns for p in (run_dir / "model.pt", run_dir / "edits.json") if p.is_file()]
        key = f"{stamps}:{view.version}".encode()
        cached, key_file = run_dir / ".thumbnail.jpg", run_dir / ".thumbnail.key"
        if cached.is_file() and key_file.is_file() and key_file.read_bytes() == key:
            return cached.read_bytes()
        frames = scene_frames(view)
        train = [f for f in frames if f.split == "train"] or frames
        if not train:
            raise HTTPException(409, "the run's scene has no frames to take a thumbnail from")
        cam = train[0].camera
        cam = cam.scaled(min(1.0, THUMBNAIL_SIDE / max(cam.width, cam.height)))
        g, _ = view.baked(0.5)
        data = _encode(render_baked(g, cam, view.run.model.config.sh_degree, np.zeros(3)).image.numpy(), "jpeg")[0]
        atomic_write_bytes(cached, data)
        atomic_write_bytes(key_file, key)
        return data

    return Response(await run_in_threadpool(work), media_type="image/jpeg", headers={"Cache-Control": "no-cache"})


@router.get("/{run_id}/frames/{index}/image", responses={200: {"content": {"image/jpeg": {}}}})
async def frame_image(request: Request, run_id: str, index: int, which: Literal["input", "sharp"] = "input") -> Response:
    """An input frame of the run's scene (or its sharp ground truth, when the scene has one)."""
    view = run_view(request.app, run_id)

    def work() -> bytes:  # reading and decoding off the event loop
        frames = scene_frames(view)
        if not 0 <= index < len(frames):
            raise HTTPException(404, f"frame {index} not in 0..{len(frames) - 1}")
        try:
            img = frames[index].image() if which == "input" else frames[index].sharp()
        except ValueError as exc:  # unreadable, or more pixels than a frame may hold
            raise HTTPException(409, f"frame {index} cannot be read: {exc}") from None
        if img is None:
            raise HTTPException(404, f"frame {index} has no sharp ground truth")
        return _encode(img, "jpeg")[0]

    return Response(await run_in_threadpool(work), media_type="image/jpeg")
