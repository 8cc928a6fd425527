"""Shared request helpers: the registry, the job runner, loaded runs, 404s by id."""

from __future__ import annotations

from pathlib import Path

from fastapi import HTTPException, Request

from kgs_core.run_view import RunView

from .jobs import JobRunner
from .registry import Workspace
from .splats import RunViews


def workspace(request: Request) -> Workspace:
    return request.app.state.ws


def jobs(request: Request) -> JobRunner:
    return request.app.state.jobs


def views(request: Request) -> RunViews:
    return request.app.state.views


def get_or_404(ws: Workspace, table: str, id_: str) -> dict:
    row = ws.get(table, id_)
    if row is None:
        raise HTTPException(status_code=404, detail=f"no {table[:-1]} with id {id_!r}")
    return row


def run_view(app, run_id: str) -> RunView:
    """The loaded model of a finished run (409 while it has no model)."""
    ws = app.state.ws
    row = get_or_404(ws, "runs", run_id)
    path = Path(row["path"])
    if not (path / "model.pt").is_file():
        raise HTTPException(status_code=409, detail=f"run {run_id} has no model yet (status: {row['status']})")
    try:
        return app.state.views.get(run_id, path)
    except ValueError as exc:
        raise HTTPException(status_code=422, detail=str(exc)) from None
