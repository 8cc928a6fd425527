"""The workspace as a whole: what the start page needs, and the built-in demo."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from kgs_core.data.synth.generate import DEFAULT_SCENE

from ..deps import jobs, workspace
from ..jobs import JobRunner
from ..registry import JobStatus, Workspace
from ..responses import DemoStarted, SystemInfo

router = APIRouter(prefix="/api", tags=["system"])


@router.get("/system", response_model=SystemInfo)
def system(request: Request, ws: Workspace = Depends(workspace)) -> dict:
    from importlib.metadata import PackageNotFoundError, version

    try:
        ver = version("kinematics-gs")
    except PackageNotFoundError:
        ver = "dev"
    return {
        "version": ver,
        "workspace": ws.root.name,
        "scenes": len(ws.list("scenes")),
        "runs": len(ws.list("runs")),
        "demo_scene": DEFAULT_SCENE,
        "token_required": bool(request.app.state.settings.token),
    }


@router.post("/demo", status_code=202, response_model=DemoStarted)
def demo(request: Request, ws: Workspace = Depends(workspace), jr: JobRunner = Depends(jobs)) -> dict:
    """Synthesize the built-in scene, then train the fast preset on it (two chained jobs)."""
    return start_demo(ws, jr)


def start_demo(ws: Workspace, jr: JobRunner) -> dict:
    from ..registry import new_id

    sid, rid = new_id(), new_id()
    scene_dir, run_dir = ws.new_dir("scenes", sid), ws.new_dir("runs", rid)
    ws.insert("scenes", id=sid, name=DEFAULT_SCENE, path=str(scene_dir), source="synth", status=JobStatus.QUEUED)
    ws.insert(
        "runs", id=rid, scene_id=sid, name=f"{DEFAULT_SCENE}-fast", path=str(run_dir), status=JobStatus.QUEUED, params={"preset": "fast"}
    )

    def then_train(status: str) -> None:
        if status == JobStatus.DONE:
            jr.start("runs", rid, "train", {"scene_dir": str(scene_dir), "run_dir": str(run_dir), "preset": "fast"})
        else:
            ws.update("runs", rid, status=JobStatus.FAILED, error=f"the demo scene could not be made ({status})")

    jr.start("scenes", sid, "synth", {"name": DEFAULT_SCENE, "out": str(scene_dir)}, on_done=then_train)
    return {"scene_id": sid, "run_id": rid}
