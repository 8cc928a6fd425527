"""The FastAPI application behind `kgs-app serve`.

`create_app(settings)` builds the app (routers under `/api`, the browser client at `/`, OpenAPI
docs at `/docs`); `serve(settings)` runs it with uvicorn. Heavy work never runs on the event
loop: renders and splat buffers go to the thread pool, training/ingest/export jobs to their own
processes (`kgs_backend.worker`).
"""

from __future__ import annotations

import errno
import sqlite3
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import Depends, FastAPI
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.exceptions import HTTPException as StarletteHTTPException

from kgs_frontend import ROOT as FRONTEND

from .jobs import JobRunner
from .registry import JobStatus, Workspace, relative_text
from .routers import exports, renders, runs, scenes, stream, system
from .schemas import finite_json
from .security import BodyLimit, HostOriginGuard, require_token
from .settings import Settings
from .splats import RunViews


def register_existing(ws: Workspace, extra: list[Path]) -> list[str]:
    """Adds scene folders and run directories not yet in the registry: everything under the
    workspace's scenes/ and runs/ (e.g. made by `kgs-app demo`) and the paths given on the
    command line. Returns the ids of the command-line paths."""
    from kgs_core.data.formats import load_scene
    from kgs_core.run import RunError, load_run

    ids = []

    def add_scene(path: Path) -> str | None:
        row = ws.find_path("scenes", path)
        if row:
            return row["id"]
        try:
            scene = load_scene(path)
        except ValueError:
            return None
        return ws.insert("scenes", name=scene.name or path.name, path=str(path.resolve()), source="path", status=JobStatus.DONE)["id"]

    def add_run(path: Path) -> str | None:
        row = ws.find_path("runs", path)
        if row:
            return row["id"]
        if not (path / "run.json").is_file():
            return None
        try:
            run = load_run(path)
            scene_id = add_scene(run.scene_path())
        except (RunError, ValueError):
            run, scene_id = None, None
        status = run.info.get("status", "done") if run else "failed"
        return ws.insert(
            "runs", scene_id=scene_id, name=path.name, path=str(path.resolve()), status=status, error=None if run else "cannot load the run"
        )["id"]

    for p in sorted((ws.root / "scenes").iterdir()):
        if p.is_dir() and not p.name.startswith("."):
            add_scene(p)
    for p in sorted((ws.root / "runs").iterdir()):
        if p.is_dir() and not p.name.startswith(".") and (p / "model.pt").is_file():
            add_run(p)
    for p in extra:
        p = Path(p)
        if not p.exists():
            raise FileNotFoundError(f"serve: {p} does not exist")
        rid = add_run(p) if (p / "run.json").is_file() else add_scene(p)
        if rid is None:
            raise ValueError(f"serve: {p} is neither a run directory nor a readable scene folder")
        ids.append(rid)
    return ids


def storage_failure(exc: Exception) -> tuple[int, str] | None:
    """`(status, message)` for a write the workspace's storage refused: a full disk or quota
    (507 Insufficient Storage) or a read-only file system or database (503); None for any
    other error. The message names the problem, not the server's paths."""
    if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return 507, "the workspace's disk is full: nothing was written; free space and retry"
    if isinstance(exc, OSError) and exc.errno == errno.EROFS:
        return 503, "the workspace is on a read-only file system: nothing was written"
    if isinstance(exc, sqlite3.OperationalError):
        text = str(exc).lower()
        if "full" in text:
            return 507, "the workspace's disk is full: the registry could not be written"
        if "readonly" in text or "read-only" in text or "disk i/o" in text or "unable to open" in text:
            return 503, "the workspace registry cannot be written (read-only or unavailable storage)"
    return None


def create_app(settings: Settings) -> FastAPI:
    ws = Workspace(settings.workspace)
    job_runner = JobRunner(ws)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        job_runner.recover()
        if settings.start_demo:
            settings.start_demo(app)
        yield
        job_runner.shutdown()

    app = FastAPI(title="Kinematics-GS", summary="Dynamic Gaussians from blurry video: runs, renders, streams.", lifespan=lifespan)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request, exc: RequestValidationError):
        # FastAPI's own handler quotes the input back and fails on a NaN it cannot encode.
        return JSONResponse(status_code=422, content={"detail": finite_json(jsonable_encoder(exc.errors()))})

    async def storage_error(request, exc: Exception):
        failure = storage_failure(exc)
        if failure is None:
            raise exc  # any other error stays a 500 (with its traceback in the server's log)
        return JSONResponse(status_code=failure[0], content={"detail": failure[1]})

    @app.exception_handler(StarletteHTTPException)
    async def without_server_paths(request, exc: StarletteHTTPException):
        # An error quoting a file (a scene that cannot load, a run's model) names it relative
        # to the workspace: the server's own layout is not the client's business.
        if isinstance(exc.detail, str):
            exc.detail = relative_text(exc.detail, ws.root)
        return await http_exception_handler(request, exc)

    app.add_exception_handler(OSError, storage_error)
    app.add_exception_handler(sqlite3.OperationalError, storage_error)

    app.state.settings = settings
    app.state.ws = ws
    app.state.jobs = job_runner
    app.state.views = RunViews()
    app.state.hub = stream.Hub()
    app.state.registered = register_existing(ws, settings.register)
    guard = [Depends(require_token)]
    for r in (system.router, scenes.router, runs.router, renders.router, exports.router):
        app.include_router(r, dependencies=guard)
    app.include_router(stream.router)  # checks the token itself (WebSocket)
    if settings.cors_origins:
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(CORSMiddleware, allow_origins=settings.cors_origins, allow_methods=["*"], allow_headers=["*"])
    # Added last, so it runs first: nothing answers a foreign Host or a cross-site write.
    app.add_middleware(BodyLimit)
    app.add_middleware(HostOriginGuard, settings=settings)
    if FRONTEND.is_dir():
        app.mount("/", StaticFiles(directory=FRONTEND, html=True), name="frontend")
    return app


def extension_ready() -> None:
    """The server never compiles: it starts with the C++ rasteriser built, or refuses to start
    saying what to run (a build inside a request held clients for a minute). Its jobs inherit
    `KGS_EXT_BUILD=0`. Without a compiler it serves with the slower torch backend."""
    import os
    import sys

    from kgs_core.render import _ext

    os.environ["KGS_EXT_BUILD"] = "0"
    try:
        _ext.load()
    except _ext.ExtensionUnavailable as exc:
        if _ext.compiler_available():
            raise SystemExit(f"kgs-app serve: {exc}") from None
        print(f"note: {exc}; serving with the (slower) torch backend", file=sys.stderr)


def serve(settings: Settings) -> None:
    import uvicorn

    app = create_app(settings)  # (refuses bad arguments first)
    extension_ready()
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    url = f"http://{host}:{settings.port}/"
    if settings.token:
        url += f"?token={settings.token}"
    print(f"Kinematics-GS serving workspace {app.state.ws.root}\n  open {url}\n  API docs http://{host}:{settings.port}/docs", flush=True)
    # No permessage-deflate: splat buffers barely compress and zlib would cost more than the scrub itself.
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="warning", ws="websockets-sansio", ws_per_message_deflate=False)
