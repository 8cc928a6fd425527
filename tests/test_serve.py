"""`kgs-app serve`: HTTP and WebSocket tests against the real FastAPI app (TestClient runs it
in-process; training and export jobs run as real worker processes)."""

from __future__ import annotations

import errno
import io
import json
import os
import shutil
import signal
import sqlite3
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi.testclient import TestClient
from PIL import Image
from starlette.websockets import WebSocketDisconnect

from kgs_backend.main import create_app
from kgs_backend.settings import Settings
from kgs_core.splat_buffer import unpack_buffer

BASE = "http://127.0.0.1:8000"  # what a browser on the default loopback bind sends as Host
WS = BASE.replace("http", "ws", 1)


@pytest.fixture
def ws_dir(tmp_path):
    return tmp_path / "workspace"


@pytest.fixture
def client(ws_dir, copy_run):
    app = create_app(Settings(workspace=ws_dir, register=[copy_run], max_upload_mb=1))
    with TestClient(app, base_url=BASE) as c:
        c.run_id = app.state.registered[0]
        c.app_ = app
        yield c


def recv_bytes(w, texts: list | None = None) -> bytes:
    while True:
        m = w.receive()
        if m.get("bytes") is not None:
            return m["bytes"]
        if m.get("type") == "websocket.close":
            raise WebSocketDisconnect(m.get("code", 1000))
        if texts is not None:
            texts.append(json.loads(m["text"]))


def recv_json_until(w, kind: str, texts: list | None = None) -> dict:
    while True:
        m = w.receive()
        if m.get("text"):
            msg = json.loads(m["text"])
            if msg["type"] == kind:
                return msg
        elif texts is not None:
            texts.append(m["bytes"])


def wait_status(c, path: str, done=("done", "failed", "cancelled", "interrupted"), timeout=240) -> dict:
    t0 = time.time()
    while time.time() - t0 < timeout:
        row = c.get(path).json()
        if row["status"] in done:
            return row
        time.sleep(0.5)
    raise AssertionError(f"{path} still {row['status']} after {timeout} s")


def test_system_docs_and_run_metadata(client):
    assert client.get("/api/system").json()["runs"] == 1
    assert "/api/runs/{run_id}/render" in client.get("/openapi.json").json()["paths"]
    runs = client.get("/api/runs").json()
    assert [r["id"] for r in runs] == [client.run_id] and runs[0]["has_model"]
    meta = client.get(f"/api/runs/{client.run_id}").json()
    assert meta["lod_levels"] == 2 and len(meta["levels"]) == 2
    assert len(meta["frames"]) >= 8 and all(0 <= f["time"] <= 1 for f in meta["frames"])
    assert sum(meta["histogram"]["counts"]) == meta["decomposition"]["gaussians"]
    assert meta["decomposition"]["dynamic"] + meta["decomposition"]["static"] == meta["decomposition"]["gaussians"]
    assert 0 < meta["decomposition"]["dynamic"] < meta["decomposition"]["gaussians"]
    assert meta["tau"] > 0
    assert meta["blur"]["camera"] == "off" and meta["blur"]["note"].startswith("exposure 0.50")


def test_openapi_documents_every_json_response(client):
    """Every JSON endpoint declares its response model, so `/docs` shows its fields; a run's
    detail validates against the model with nothing left over (extra fields are refused)."""
    from kgs_backend.responses import RunDetail

    api = client.get("/openapi.json").json()
    untyped = []
    for path, ops in api["paths"].items():
        for method, op in ops.items():
            for code, resp in op.get("responses", {}).items():
                schema = resp.get("content", {}).get("application/json", {}).get("schema")
                # (the training log's rows are typed as {column: number or null}: no model of their own)
                # (binary endpoints — renders, frame images, downloads — have an empty JSON schema)
                if code.startswith("2") and schema and "$ref" not in json.dumps(schema) and not path.endswith("/log"):
                    untyped.append(f"{method.upper()} {path}")
    assert untyped == [], untyped
    props = api["components"]["schemas"]["RunDetail"]["properties"]
    assert {"frames", "decomposition", "histogram", "edits", "progress", "resumable"} <= set(props)
    RunDetail.model_validate(client.get(f"/api/runs/{client.run_id}").json())


def test_render_png_sets_and_bad_parameters(client):
    rid = client.run_id
    r = client.get(f"/api/runs/{rid}/render", params={"t": 0.5})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    full = np.asarray(Image.open(io.BytesIO(r.content)))
    assert full.shape == (48, 48, 3) and full.std() > 5
    stat = np.asarray(Image.open(io.BytesIO(client.get(f"/api/runs/{rid}/render", params={"t": 0.5, "set": "static"}).content)))
    dyn = np.asarray(Image.open(io.BytesIO(client.get(f"/api/runs/{rid}/render", params={"t": 0.5, "set": "dynamic"}).content)))
    assert np.abs(stat.astype(int) - full).mean() > 0.5 and np.abs(dyn.astype(int) - full).mean() > 0.5
    big = client.get(f"/api/runs/{rid}/render", params={"t": 0.5, "width": 96, "height": 64, "format": "jpeg"})
    assert np.asarray(Image.open(io.BytesIO(big.content))).shape == (64, 96, 3)
    for params in ({"t": 2}, {"set": "moving"}, {"lod": 0}, {"viewmat": "1,2,3"}, {"frame": 10_000}, {"width": 100000}):
        assert client.get(f"/api/runs/{rid}/render", params=params).status_code == 422, params
    assert client.get("/api/runs/nope/render").status_code == 404
    assert client.get(f"/api/runs/{rid}/frames/0/image").headers["content-type"] == "image/jpeg"
    assert client.get(f"/api/runs/{rid}/frames/999/image").status_code == 404


def test_stream_static_once_then_dynamic_and_coalescing(client):
    rid = client.run_id
    meta = client.get(f"/api/runs/{rid}").json()
    with client.websocket_connect(WS + f"/api/runs/{rid}/stream") as w:
        w.send_json({"type": "subscribe", "velocity": True})
        h, rec, _ = unpack_buffer(recv_bytes(w))
        assert h["kind"] == "static" and h["count"] == meta["decomposition"]["static_kept"]
        assert len(set(rec["index"].tolist())) == len(rec)
        w.send_json({"type": "time", "t": 0.0, "seq": 0})
        h0, rec0, vel0 = unpack_buffer(recv_bytes(w))
        assert h0["kind"] == "dynamic" and h0["count"] == meta["decomposition"]["dynamic_kept"] and vel0.shape == (len(rec0), 3)
        assert set(rec0["index"].tolist()).isdisjoint(rec["index"].tolist())
        recv_json_until(w, "answered")
        # A burst of scrub requests: the latest wins, the ones in between are dropped.
        for i in range(1, 21):
            w.send_json({"type": "time", "t": i / 20, "seq": i})
        buffers = []
        last = None
        while last is None or last["seq"] != 20:
            last = recv_json_until(w, "answered", buffers)
        assert len(buffers) < 20
        h1, rec1, _ = unpack_buffer(buffers[-1])
        assert h1["t"] == 1.0
        moved = np.linalg.norm(rec1["position"] - rec0["position"], axis=1)
        assert moved.max() > 1e-3  # the dynamic set moves between t = 0 and t = 1
        # Covariances survive the float16 packing: symmetric PSD diagonals.
        cov = rec1["covariance"].astype(np.float64) * h1["cov_scale"]
        assert np.all(cov[:, [0, 3, 5]] > 0)
        # Malformed messages get an error and the socket stays usable.
        w.send_text("{not json")
        assert "JSON" in recv_json_until(w, "error")["message"]
        w.send_json({"type": "time", "t": 7})
        assert "time.t: Input should be less than or equal to 1" in recv_json_until(w, "error")["message"]
        w.send_json({"type": "time", "t": 0.5, "colour": "red"})  # an unknown field is named
        assert "colour" in recv_json_until(w, "error")["message"]
        w.send_json({"type": "teleport"})
        assert "teleport" in recv_json_until(w, "error")["message"]
        w.send_json({"type": "ping"})
        recv_json_until(w, "pong")


def test_live_tau_pushes_new_sets(client):
    rid = client.run_id
    before = client.get(f"/api/runs/{rid}").json()["decomposition"]
    with client.websocket_connect(WS + f"/api/runs/{rid}/stream") as w:
        w.send_json({"type": "subscribe"})
        recv_bytes(w)
        r = client.post(f"/api/runs/{rid}/tau", json={"tau": before["tau"] * 10})
        after = r.json()
        assert after["dynamic"] < before["dynamic"] and after["version"] == before["version"] + 1
        decomposition = recv_json_until(w, "decomposition")
        assert decomposition["dynamic"] == after["dynamic"]
        h, rec, _ = unpack_buffer(recv_bytes(w))
        assert h["kind"] == "static" and h["count"] == after["static_kept"]
        # tau over the socket too
        w.send_json({"type": "tau", "tau": before["tau"]})
        assert recv_json_until(w, "decomposition")["dynamic"] == before["dynamic"]
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": -1}).status_code == 422
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": "x"}).status_code == 422
    assert client.post(f"/api/runs/{rid}/tau", content=b"{oops", headers={"content-type": "application/json"}).status_code == 422


def test_edits_change_sets_and_are_stored(client, copy_run):
    rid = client.run_id
    with client.websocket_connect(WS + f"/api/runs/{rid}/stream") as w:
        w.send_json({"type": "subscribe"})
        _, rec, _ = unpack_buffer(recv_bytes(w))
        victims = rec["index"][:5].tolist()
        r = client.post(f"/api/runs/{rid}/edits", json={"op": "delete", "indices": victims})
        assert r.status_code == 200 and r.json()["static_kept"] == len(rec) - 5
        _, rec2, _ = unpack_buffer(recv_bytes(w))
        assert len(rec2) == len(rec) - 5 and not set(victims) & set(rec2["index"].tolist())
    stored = json.loads((copy_run / "edits.json").read_text())
    assert sorted(stored["levels"]["2"]["deleted"]) == sorted(victims)
    assert client.post(f"/api/runs/{rid}/edits", json={"op": "delete", "indices": [10**9]}).status_code == 422
    assert client.post(f"/api/runs/{rid}/edits", json={"op": "explode"}).status_code == 422
    assert (
        client.post(f"/api/runs/{rid}/edits", json={"op": "restore"}).json()["kept"]
        == client.get(f"/api/runs/{rid}").json()["decomposition"]["gaussians"]
    )


def test_undo_and_redo_walk_the_edit_history_and_survive_a_reload(client, copy_run):
    """Each edit (a crop included) can be undone and redone; the history is in edits.json, so a
    fresh view of the run (a reload, a restarted server) keeps the undone state; a new edit
    drops what could be redone; a hand-broken history is refused naming the field."""
    from kgs_core.edits import EditsError, load_edits
    from kgs_core.run_view import RunView

    rid = client.run_id
    edit = lambda **body: client.post(f"/api/runs/{rid}/edits", json=body)  # noqa: E731
    total = client.get(f"/api/runs/{rid}").json()["decomposition"]["gaussians"]
    assert edit(op="undo").status_code == 422  # nothing to undo yet
    assert edit(op="delete", indices=[0, 1, 2]).json()["kept"] == total - 3
    cropped = edit(op="crop", crop={"min": [-0.01, -0.01, -0.01], "max": [0.01, 0.01, 0.01]}).json()
    assert cropped["kept"] < total - 3 and cropped["history"]["undo"] == "crop"
    undone = edit(op="undo").json()
    assert undone["kept"] == total - 3 and undone["history"] == {
        "undo": "delete 3 splats",
        "undo_steps": 1,
        "redo": "crop",
        "redo_steps": 1,
    }
    stored = json.loads((copy_run / "edits.json").read_text())
    assert stored["crop"] is None and [s["label"] for s in stored["history"]["redo"]] == ["crop"]
    reloaded = RunView(copy_run)  # what a reload or a restarted server reads
    assert reloaded.edits.crop_min is None and reloaded.decomposition()["kept"] == total - 3
    assert edit(op="redo").json()["kept"] == cropped["kept"]
    assert edit(op="undo").json()["kept"] == total - 3
    assert edit(op="undo").json()["kept"] == total  # back to the start
    assert edit(op="redo").json()["history"]["redo"] == "crop"
    after = edit(op="hide", indices=[5]).json()  # a new edit: the undone crop cannot come back
    assert after["history"]["redo"] is None and edit(op="redo").status_code == 422
    assert after["history"]["undo_steps"] == 2
    stored = json.loads((copy_run / "edits.json").read_text())
    stored["history"]["undo"][0]["layer"] = {"crop": {"min": [1, 1, 1], "max": [0, 0, 0]}}
    (copy_run / "edits.json").write_text(json.dumps(stored))
    with pytest.raises(EditsError, match=r"history.undo\[0\]: crop.min must not exceed"):
        load_edits(copy_run)
    assert edit(op="clear").json()["kept"] == total  # (the server's copy was valid)


def test_runs_list_tells_runs_apart(client):
    (run,) = client.get("/api/runs").json()
    assert run["scene_name"] == "bounce"
    assert run["folder"].startswith("runs/") and not run["folder"].startswith("/")
    assert run["created"] > 0


def test_unknown_ids(client):
    for path in ("/api/runs/abc", "/api/scenes/abc", "/api/exports/abc", "/api/exports/abc/download"):
        assert client.get(path).status_code == 404, path
    assert client.delete("/api/runs/abc").status_code == 404
    assert client.post("/api/runs", json={"scene_id": "abc"}).status_code == 404
    with client.websocket_connect(WS + "/api/runs/abc/stream") as w:
        assert w.receive() == {"type": "websocket.close", "code": 4404, "reason": "no run with id 'abc'"}


def test_websocket_refusals_on_a_real_server(copy_run, tmp_path):
    """Against uvicorn, not TestClient (which shows close codes a real server never sent): a
    missing or wrong token closes with 4401 and an unknown run with 4404, after the handshake,
    so a browser sees the code; a foreign Origin is refused at the handshake (HTTP 403)."""
    from websockets.exceptions import ConnectionClosed, InvalidStatus
    from websockets.sync.client import connect

    from kgs_backend.launch import ServerProcess

    with ServerProcess([copy_run], tmp_path / "workspace", token="s3cret") as srv:
        base, rid = srv.base.replace("http", "ws", 1), srv.runs[0]["id"]
        for path, code in (
            (f"/api/runs/{rid}/stream", 4401),
            (f"/api/runs/{rid}/stream?token=wrong", 4401),
            ("/api/runs/nope/stream?token=s3cret", 4404),
        ):
            with connect(base + path, open_timeout=30) as w, pytest.raises(ConnectionClosed) as exc:
                w.recv(timeout=30)
            assert exc.value.rcvd is not None and exc.value.rcvd.code == code, path
        with pytest.raises(InvalidStatus) as exc:
            connect(base + f"/api/runs/{rid}/stream?token=s3cret", origin="http://evil.example", open_timeout=30)
        assert exc.value.response.status_code == 403
        with connect(base + f"/api/runs/{rid}/stream?token=s3cret", open_timeout=30) as w:
            w.send(json.dumps({"type": "subscribe"}))
            while isinstance(msg := w.recv(timeout=60), str):
                pass
            assert unpack_buffer(msg)[0]["kind"] == "static"


def test_a_copied_workspace_uses_its_own_folders(copy_run):
    """Paths are stored relative to the workspace (the registry and run.json): a copy lists
    each run once, and its edits and renders use the copy's files, not the original's."""
    original = copy_run.parent.parent  # a workspace layout: runs/<name>, scenes/bounce
    with TestClient(create_app(Settings(workspace=original)), base_url=BASE) as c:
        assert len(c.get("/api/runs").json()) == 1
    copy = original.parent / "moved"
    shutil.copytree(original, copy)
    app = create_app(Settings(workspace=copy))
    with TestClient(app, base_url=BASE) as c:
        runs = c.get("/api/runs").json()
        assert len(runs) == 1 and len(c.get("/api/scenes").json()) == 1
        rid = runs[0]["id"]
        row = app.state.ws.get("runs", rid)
        assert Path(row["path"]).is_relative_to(copy.resolve())
        with sqlite3.connect(copy / "workspace.db") as db:
            assert not any(Path(p).is_absolute() for (p,) in db.execute("SELECT path FROM runs UNION SELECT path FROM scenes"))
        assert c.post(f"/api/runs/{rid}/edits", json={"op": "delete", "indices": [0]}).status_code == 200
        assert c.get(f"/api/runs/{rid}/frames/0/image").status_code == 200
        from kgs_backend.deps import run_view

        assert run_view(app, rid).run.scene_path().resolve().is_relative_to(copy.resolve())
    assert (copy / "runs" / copy_run.name / "edits.json").is_file()
    assert not (copy_run / "edits.json").exists()


def test_token_required_when_set(ws_dir, copy_run):
    app = create_app(Settings(workspace=ws_dir, register=[copy_run], token="s3cret"))
    with TestClient(app, base_url=BASE) as c:
        rid = app.state.registered[0]
        assert c.get("/api/system").status_code == 401
        assert c.get("/api/runs", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert c.get("/api/runs", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert c.get("/api/runs", params={"token": "s3cret"}).status_code == 200
        assert c.get(f"/api/runs/{rid}/render", headers={"X-KGS-Token": "s3cret"}).status_code == 200
        assert c.get("/").status_code == 200  # the page itself holds no data; the API needs the token
        with c.websocket_connect(WS + f"/api/runs/{rid}/stream") as w:
            assert w.receive()["code"] == 4401
        with c.websocket_connect(WS + f"/api/runs/{rid}/stream?token=s3cret") as w:
            w.send_json({"type": "subscribe"})
            assert unpack_buffer(recv_bytes(w))[0]["kind"] == "static"


def _zip_dir(folder: Path) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for p in folder.rglob("*"):
            if p.is_file():
                z.write(p, Path("data") / p.relative_to(folder))
    return buf.getvalue()


def test_uploads_limits_and_types(client, tiny_run, tmp_path):
    scene_dir = tiny_run.parent.parent / "scenes" / "bounce"
    small = tmp_path / "small"
    shutil.copytree(scene_dir, small, ignore=shutil.ignore_patterns("sharp", "mask", "motion"))
    blob = _zip_dir(small)
    assert len(blob) < 1024 * 1024, "fixture scene must fit the 1 MB test limit"
    zip_type = {"content-type": "application/zip"}
    r = client.post("/api/scenes/upload", params={"name": "up", "kind": "zip"}, content=blob, headers=zip_type)
    assert r.status_code == 201, r.text
    assert r.json()["frames"] >= 8 and r.json()["status"] == "done"
    assert client.get(f"/api/scenes/{r.json()['id']}").json()["train_frames"] >= 8
    big = b"PK\x03\x04" + b"\0" * (1024 * 1024 + 10)
    assert client.post("/api/scenes/upload", params={"name": "big", "kind": "zip"}, content=big, headers=zip_type).status_code == 413
    assert client.post("/api/scenes/upload", params={"name": "x", "kind": "zip"}, content=b"hello", headers=zip_type).status_code == 415
    assert (
        client.post(
            "/api/scenes/upload", params={"name": "x", "kind": "video"}, content=b"not a video", headers={"content-type": "video/mp4"}
        ).status_code
        == 415
    )
    assert client.post("/api/scenes/upload", params={"name": "../x", "kind": "zip"}, content=blob, headers=zip_type).status_code == 422
    assert client.post("/api/scenes/upload", params={"name": "x", "kind": "exe"}, content=blob, headers=zip_type).status_code == 422
    evil = io.BytesIO()
    with zipfile.ZipFile(evil, "w") as z:
        z.writestr("../../escape.txt", "x")
    assert (
        client.post("/api/scenes/upload", params={"name": "x", "kind": "zip"}, content=evil.getvalue(), headers=zip_type).status_code == 422
    )
    junk = io.BytesIO()
    with zipfile.ZipFile(junk, "w") as z:
        z.writestr("readme.txt", "no dataset here")
    assert (
        client.post("/api/scenes/upload", params={"name": "x", "kind": "zip"}, content=junk.getvalue(), headers=zip_type).status_code == 422
    )
    # Nothing half-written stays behind.
    ws_root = client.app_.state.ws.root
    assert not [p for p in (ws_root / "scenes").iterdir() if p.name.startswith(".upload")]
    assert len(client.get("/api/scenes").json()) == 2  # the registered run's scene and the upload


def test_training_job_progress_cancel_restart_and_export(client, ws_dir):
    scene_id = client.get(f"/api/runs/{client.run_id}").json()["scene_id"]
    assert client.post("/api/runs", json={"scene_id": scene_id, "preset": "nope"}).status_code == 422
    assert client.post("/api/runs", json={"scene_id": scene_id, "ablate": ["everything"]}).status_code == 422
    bad_blur = client.post("/api/runs", json={"scene_id": scene_id, "camera_blur": "yes"})
    assert bad_blur.status_code == 422 and "camera_blur" in bad_blur.text
    if not torch.cuda.is_available():  # a GPU this machine lacks is refused before a job is queued
        no_gpu = client.post("/api/runs", json={"scene_id": scene_id, "device": "cuda"})
        assert no_gpu.status_code == 422 and "device cuda" in no_gpu.text, no_gpu.text
    for settings, needle in (
        (["lambda_regg=0.1"], "lambda_regg"),
        (["model.knn=1.5"], "model.knn takes a whole number"),
        (["frame_sampling=often"], "frame_sampling must be one of"),
    ):
        bad = client.post("/api/runs", json={"scene_id": scene_id, "settings": settings})
        assert bad.status_code == 422 and needle in bad.text, bad.text
    r = client.post("/api/runs", json={"scene_id": scene_id, "iterations": 40, "settings": ["model.knn=4", "lambda_reg=0.02"]})
    assert r.status_code == 202
    done = wait_status(client, f"/api/runs/{r.json()['id']}")
    assert done["status"] == "done" and done["has_model"] and done["iteration"] == 40
    config = json.loads((ws_dir / "runs" / done["folder"].split("/")[-1] / "run.json").read_text())["config"]
    assert config["model"]["knn"] == 4 and config["lambda_reg"] == 0.02  # the settings reached the training
    assert done["progress"]["iteration"] == 40 and done["progress"]["gaussians"] > 0
    assert len(client.get(f"/api/runs/{done['id']}/log").json()) >= 2
    # A long run: progress streams, cancel keeps a model.
    long = client.post("/api/runs", json={"scene_id": scene_id, "iterations": 100000}).json()
    with client.websocket_connect(WS + f"/api/runs/{long['id']}/stream") as w:
        p = recv_json_until(w, "progress")
        assert p["iteration"] >= 1 and p["iterations"] == 100000 and "loss" in p
        assert client.post(f"/api/runs/{long['id']}/cancel").status_code == 200
        st = recv_json_until(w, "status")
        assert st["status"] == "cancelled"
    assert client.post(f"/api/runs/{long['id']}/cancel").status_code == 409
    stopped = client.get(f"/api/runs/{long['id']}").json()
    assert stopped["has_model"] and stopped["resumable"]
    # Resume continues from the checkpoint; a worker killed by a signal leaves the run
    # "interrupted" (not failed), resumable again.
    assert client.post(f"/api/runs/{long['id']}/resume").status_code == 202
    deadline = time.time() + 120
    while (client.get(f"/api/runs/{long['id']}").json().get("progress") or {}).get("iteration", 0) <= stopped["iteration"]:
        assert time.time() < deadline, "the resumed run made no progress"
        time.sleep(0.3)
    os.kill(client.app_.state.ws.get("runs", long["id"])["pid"], signal.SIGKILL)
    killed = wait_status(client, f"/api/runs/{long['id']}", done=("interrupted", "failed"))
    assert killed["status"] == "interrupted" and "resume" in killed["error"] and killed["resumable"], killed
    # A failing job keeps its error.
    bad = client.app_.state.ws.insert("scenes", name="broken", path=str(ws_dir / "scenes" / "broken"), source="upload", status="done")
    (ws_dir / "scenes" / "broken").mkdir()
    (ws_dir / "scenes" / "broken" / "dataset.json").write_text("{")
    failed = wait_status(client, f"/api/runs/{client.post('/api/runs', json={'scene_id': bad['id']}).json()['id']}")
    assert failed["status"] == "failed" and "scenes/broken/dataset.json" in failed["error"]
    assert str(ws_dir.resolve()) not in failed["error"]  # the workspace's own path is not told
    # Export as a job, then download.
    e = client.post(f"/api/runs/{done['id']}/exports", json={"format": "splat", "times": "0.5"}).json()
    e = wait_status(client, f"/api/exports/{e['id']}")
    assert e["status"] == "done", e
    got = client.get(f"/api/exports/{e['id']}/download")
    blob = got.content
    # Named after the run (its name, made safe for a file name), not its id.
    run_name = client.get(f"/api/runs/{done['id']}").json()["name"]
    safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in run_name).strip("._")
    assert f'filename="{safe}-' in got.headers["content-disposition"], got.headers["content-disposition"]
    with zipfile.ZipFile(io.BytesIO(blob)) as z:
        names = z.namelist()
        assert "frame_00000.splat" in names and len(z.read("frame_00000.splat")) % 32 == 0
    assert client.post(f"/api/runs/{done['id']}/exports", json={"format": "obj"}).status_code == 422
    # Fine-tune from a new decomposition: a new run starting from this model, decomposed at the given tau.
    tau = client.get(f"/api/runs/{done['id']}").json()["tau"] * 5
    ft = client.post(f"/api/runs/{done['id']}/finetune", json={"tau": tau, "iterations": 20}).json()
    ft = wait_status(client, f"/api/runs/{ft['id']}")
    assert ft["status"] == "done" and ft["iteration"] == 20, ft
    meta = client.get(f"/api/runs/{ft['id']}").json()
    assert meta["tau"] == pytest.approx(tau) and meta["decomposition"]["gaussians"] == done["gaussians"]
    assert client.post("/api/runs/nope/finetune", json={}).status_code == 404
    assert client.post(f"/api/runs/{done['id']}/resume").status_code == 409  # it finished
    # A run.json whose configuration is malformed is refused with the field named, not a 500.
    info_path = Path(client.app_.state.ws.get("runs", done["id"])["path"]) / "run.json"
    info = json.loads(info_path.read_text())
    info["config"]["densify"]["grad_treshold"] = 1e-4
    info_path.write_text(json.dumps(info))
    bad_ft = client.post(f"/api/runs/{done['id']}/finetune", json={"tau": tau, "iterations": 20})
    assert bad_ft.status_code == 409 and "run.json: densify.grad_treshold is not a setting" in bad_ft.json()["detail"]
    # A restarted server lists the earlier runs and their states.
    app2 = create_app(Settings(workspace=ws_dir))
    with TestClient(app2, base_url=BASE) as c2:
        statuses = {r["id"]: r["status"] for r in c2.get("/api/runs").json()}
    assert statuses[done["id"]] == "done" and statuses[long["id"]] == "interrupted" and statuses[failed["id"]] == "failed"
    # Deleting a run deletes its exports: their files are no longer downloadable.
    assert client.delete(f"/api/runs/{done['id']}").status_code == 204
    assert client.get(f"/api/exports/{e['id']}/download").status_code == 404
    assert not (ws_dir / "exports" / e["id"]).exists()


def test_exact_dynamic_buffer_without_velocities_is_the_same_set(copy_run):
    """A client that does not show velocities gets the same dynamic splats from the exact
    path (which then skips the velocity's field samples at exposure 0), without the block."""
    from kgs_core.run_view import RunView

    view = RunView(copy_run)
    h_v, rec_v, vel = unpack_buffer(view.dynamic_buffer(0.3, velocity=True, exact=True))
    h_n, rec_n, no_vel = unpack_buffer(view.dynamic_buffer(0.3, velocity=False, exact=True))
    assert h_v["velocity"] and vel.shape == (len(rec_v), 3) and len(rec_v) > 0
    assert not h_n["velocity"] and no_vel is None
    assert np.array_equal(rec_n["index"], rec_v["index"])
    assert np.allclose(rec_n["position"].astype(np.float64), rec_v["position"].astype(np.float64), atol=1e-3)
    assert np.allclose(rec_n["covariance"].astype(np.float64), rec_v["covariance"].astype(np.float64), atol=1e-3)


def test_the_view_at_the_runs_own_tau_shows_the_split_training_made(copy_run):
    """At the run's τ the viewer shows the trained model: the decomposition training made (here with
    the Gaussians the decompositions' flow reading added, whose K is under τ) and its canonical
    means, not a re-decomposition by K that turns those static and moves their neighbours."""
    from kgs_core.run import load_torch, save_torch
    from kgs_core.run_view import RunView

    # What the flow reading leaves, made sure of in every level: dynamic Gaussians whose K is under τ.
    state = load_torch(copy_run / "model.pt")
    for level in [state["model"], *state.get("levels", [])]:
        tau = state["model"]["config"]["tau"]
        dynamic = torch.nonzero(level["dynamic"]).squeeze(1)
        level["K"][dynamic[::2]] = tau / 2
    save_torch(copy_run / "model.pt", state)
    view = RunView(copy_run)
    lod, m = view.model(None)
    trained = view.run.level(lod)
    assert view.tau == trained.config.tau
    assert (trained.dynamic & (trained.K <= view.tau)).any()  # what K alone would not call dynamic
    assert torch.equal(m.dynamic, trained.dynamic)
    assert torch.equal(m.params.means, trained.params.means.detach())


def test_live_tau_keeps_gaussians_that_turn_static_where_they_were_drawn(copy_run):
    """A higher τ in the viewer turns Gaussians static in place: each is drawn at its
    time-averaged position, not at its canonical mean; the run's own model is not touched, and
    τ changes do not add up."""
    from kgs_core.run_view import RunView

    view = RunView(copy_run)
    lod, m0 = view.model(None)
    own = view.run.level(lod).params.means.detach().clone()
    average = own + m0.mean_offsets()[:, :3]
    tau = view.tau
    for _ in range(2):  # the same τ twice, from the run's own model both times
        view.set_tau(tau * 10)
        _, m1 = view.model(lod)
        turned = m0.dynamic & ~m1.dynamic
        assert int(turned.sum()) > 0
        torch.testing.assert_close(m1.params.means[turned], average[turned], atol=1e-6, rtol=0)
        assert float((average - own)[turned].norm(dim=-1).max()) > 1e-4  # a plain decomposition would move them
    assert torch.equal(view.run.level(lod).params.means.detach(), own)


def test_trajectory_cache_gives_the_exact_set_at_its_samples_and_the_linear_mix_between(copy_run):
    """The cache's buffers: at a sample time the exact evaluation's splats (to float16), halfway
    between two samples their mean, and after an edit only the Gaussians the edit keeps."""
    from kgs_core.run_view import RunView

    view = RunView(copy_run)
    lod = view.run.n_levels
    view.trajectories(lod, 0.0)
    tr = view._trajectories[(lod, view.version, 0.0)]
    assert tr.ready.wait(60) and tr.failed is None

    def splats(buf):
        h, rec, vel = unpack_buffer(buf)
        return h, rec["index"], rec["position"].astype(np.float64), rec["covariance"] * h["cov_scale"], vel

    t0, t1 = (float(t) for t in tr.times[2:4])
    ha, ia, pa, ca, va = splats(view.dynamic_buffer(t0))
    hb, ib, pb, cb, vb = splats(view.dynamic_buffer(t0, exact=True))
    assert ha["interpolated"] and not hb["interpolated"] and len(ia) > 0
    assert np.array_equal(ia, ib) and np.allclose(pa, pb, atol=1e-6)
    assert np.allclose(ca, cb, rtol=2e-3, atol=1e-3 * ha["cov_scale"])
    assert np.allclose(va.astype(np.float64), vb.astype(np.float64), rtol=2e-3, atol=1e-3)
    _, _, p1, c1, _ = splats(view.dynamic_buffer(t1, exact=True))
    _, im, pm, cm, _ = splats(view.dynamic_buffer((t0 + t1) / 2))
    assert np.array_equal(im, ia) and np.allclose(pm, (pb + p1) / 2, atol=1e-6)
    assert np.allclose(cm, (cb + c1) / 2, rtol=2e-3, atol=1e-3 * ha["cov_scale"])
    # An edit makes a new version: its cache leaves the deleted Gaussians out.
    gone = [int(i) for i in ia[:3]]
    view.apply_edit("delete", lod, gone)
    view.trajectories(lod, 0.0)
    assert view._trajectories[(lod, view.version, 0.0)].ready.wait(60)
    h, idx, *_ = splats(view.dynamic_buffer(t0))
    assert h["interpolated"] and len(idx) == len(ia) - 3 and not set(gone) & set(idx.tolist())


def test_trajectory_cache_fades_gaussians_present_for_part_of_the_clip_as_the_model_does(copy_run):
    """Spawned Gaussians (a bounded `lifespan`) come and go in time: the cache's interpolated
    buffers give them the alpha the exact evaluation gives, at the lifespan's centre and away
    from it."""
    import torch

    from kgs_core.run_view import RunView

    view = RunView(copy_run)
    lod = view.run.n_levels
    m = view.run.model
    some = torch.nonzero(m.dynamic).squeeze(1)[:4]
    m.lifespan[some] = torch.tensor([[0.3, 0.05], [0.35, 0.02], [0.6, 0.1], [0.3, 0.3]])
    m.params.opacity_logits.data[some] = 3.0  # opacity 0.953: alpha 243 where fully present
    full = int(torch.sigmoid(torch.tensor(3.0)) * 255 + 0.5)
    view.trajectories(lod, 0.0)
    assert view._trajectories[(lod, view.version, 0.0)].ready.wait(60)
    for t in (0.3, 0.33, 0.5):
        h, rec, _ = unpack_buffer(view.dynamic_buffer(t))
        he, rec_e, _ = unpack_buffer(view.dynamic_buffer(t, exact=True))
        assert h["interpolated"] and not he["interpolated"]
        assert np.array_equal(rec["index"], rec_e["index"])
        alpha, alpha_e = rec["rgba"][:, 3].astype(int), rec_e["rgba"][:, 3].astype(int)
        assert np.abs(alpha - alpha_e).max() <= 1
        row = {int(i): k for k, i in enumerate(rec["index"])}
        if t == 0.3:
            assert alpha[row[int(some[0])]] == full
        if t == 0.5:  # 7.5 widths from the second one's centre: gone; the last one (width 0.3) is not
            assert alpha[row[int(some[1])]] == 0 and alpha[row[int(some[3])]] == round(full * np.exp(-0.5 * (2 / 3) ** 2))


def test_trajectory_cache_gives_a_time_opacity_the_alpha_the_model_does(copy_run):
    """With `model.time_opacity` the dynamic Gaussians' alpha changes with time: the cache
    samples it with the positions, so that its buffers at the samples give the exact
    evaluation's alpha, and between them an interpolation of it."""
    import torch

    from kgs_core.model.deformation import TimeOpacity
    from kgs_core.run_view import RunView

    view = RunView(copy_run)
    lod = view.run.n_levels
    m = view.run.model
    m.time_opacity = TimeOpacity(m.config.feature_dim)
    with torch.no_grad():
        m.time_opacity.mlp[-1].weight.normal_(0, 2.0, generator=torch.Generator().manual_seed(0))
    view.trajectories(lod, 0.0)
    cache = view._trajectories[(lod, view.version, 0.0)]
    assert cache.ready.wait(60)
    spread = []
    for t in (float(cache.times[3]), float(cache.times[7])):
        h, rec, _ = unpack_buffer(view.dynamic_buffer(t))
        he, rec_e, _ = unpack_buffer(view.dynamic_buffer(t, exact=True))
        assert h["interpolated"] and np.array_equal(rec["index"], rec_e["index"])
        alpha, alpha_e = rec["rgba"][:, 3].astype(int), rec_e["rgba"][:, 3].astype(int)
        assert np.abs(alpha - alpha_e).max() <= 1
        spread.append(alpha_e)
    assert np.abs(spread[0] - spread[1]).max() > 20  # the net does change alpha with time


# ------------------------------------------------------------ hostile clients


def test_foreign_host_and_cross_site_writes_are_refused(client):
    """DNS rebinding (a foreign Host) and cross-site writes (a foreign Origin on a POST, which a
    web page can send as text/plain without a preflight) on the no-token loopback default."""
    rid = client.run_id
    assert client.get("/api/runs", headers={"host": "attacker.example"}).status_code == 400
    assert client.get("/", headers={"host": "attacker.example:8000"}).status_code == 400
    assert client.get("/api/runs", headers={"host": "localhost:8000"}).status_code == 200
    assert client.get("/api/runs", headers={"host": "[::1]:8000"}).status_code == 200
    evil = {"origin": "http://evil.example", "content-type": "text/plain"}
    r = client.post("/api/scenes/upload", params={"name": "x", "kind": "zip"}, content=b"PK\x03\x04", headers=evil)
    assert r.status_code == 403 and "cross-origin" in r.json()["detail"]
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": 1e-4}, headers={"origin": "http://evil.example"}).status_code == 403
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": 1e-4}, headers={"origin": "null"}).status_code == 403
    # The server's own page (same host and port) and non-browser clients (no Origin) may write.
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": 1e-4}, headers={"origin": BASE}).status_code == 200
    assert client.post(f"/api/runs/{rid}/tau", json={"tau": 1e-4}).status_code == 200
    # Reads from a foreign origin get no CORS headers (CORS is off), so the browser hides them.
    assert "access-control-allow-origin" not in client.get("/api/runs", headers={"origin": "http://evil.example"}).headers
    # Uploads need their declared content type: text/plain is refused even same-origin.
    r = client.post(
        "/api/scenes/upload", params={"name": "x", "kind": "zip"}, content=b"PK\x03\x04", headers={"content-type": "text/plain"}
    )
    assert r.status_code == 415 and "application/zip" in r.json()["detail"]
    with pytest.raises(WebSocketDisconnect):
        with client.websocket_connect(WS + f"/api/runs/{rid}/stream", headers={"origin": "http://evil.example"}) as w:
            w.receive()
    with client.websocket_connect(WS + f"/api/runs/{rid}/stream", headers={"origin": BASE}) as w:
        w.send_json({"type": "ping"})
        recv_json_until(w, "pong")


def test_allowed_hosts_and_wildcard_bind(ws_dir, copy_run):
    from kgs_backend.security import host_allowed

    assert host_allowed("kgs.lab.example:443", "127.0.0.1", ["kgs.lab.example"])
    assert not host_allowed("other.example", "127.0.0.1", ["kgs.lab.example"])
    assert host_allowed("anything.example", "0.0.0.0", [])  # every interface: the token guards it
    assert not host_allowed("anything.example", "0.0.0.0", ["kgs.lab.example"])
    app = create_app(Settings(workspace=ws_dir, register=[copy_run], allowed_hosts=["kgs.lab.example"]))
    with TestClient(app, base_url="https://kgs.lab.example") as c:
        assert c.get("/api/runs").status_code == 200


def test_stream_survives_binary_frames_and_bad_lod(client):
    rid = client.run_id
    with client.websocket_connect(WS + f"/api/runs/{rid}/stream") as w:
        w.send_bytes(b"\x00\x01binary")
        assert "binary" in recv_json_until(w, "error")["message"]
        for lod in (0, 99):
            w.send_json({"type": "subscribe", "lod": lod})
            assert "lod must be in 1..2" in recv_json_until(w, "error")["message"]
        w.send_json({"type": "subscribe", "lod": 1})
        assert unpack_buffer(recv_bytes(w))[0]["kind"] == "static"


def test_unread_messages_are_bounded():
    """A client that sends without reading (a ping flood) cannot grow the server: pongs
    coalesce, anything else past MAX_NOTES disconnects it."""
    from kgs_backend.routers.stream import MAX_NOTES, Connection

    conn = Connection(ws=None, run_id="r")
    for _ in range(10_000):
        conn.notify({"type": "pong"})
    assert len(conn.notes) == 1 and not conn.overflow
    for i in range(10_000):
        conn.notify({"type": "error", "message": str(i)})
    assert len(conn.notes) == MAX_NOTES and conn.overflow


def test_concurrent_first_downloads_of_a_folder_export(tmp_path):
    """Six threads download a folder export at once: all get the same complete zip, and no
    temporary file stays behind."""
    from concurrent.futures import ThreadPoolExecutor

    from kgs_backend.routers.exports import zipped

    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(40):
        (folder / f"{i:03d}.ply").write_bytes(np.random.default_rng(i).bytes(20_000))
    with ThreadPoolExecutor(6) as pool:
        archives = list(pool.map(lambda _: zipped(folder), range(6)))
    assert len(set(archives)) == 1
    with zipfile.ZipFile(archives[0]) as z:
        assert len(z.namelist()) == 40 and z.testzip() is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "frames.zip"]


def test_non_finite_numbers_big_bodies_and_huge_seeds_get_4xx(client):
    rid = client.run_id
    scene_id = client.get(f"/api/runs/{rid}").json()["scene_id"]
    js = {"content-type": "application/json"}
    for path, body in (
        (f"/api/runs/{rid}/tau", b'{"tau": NaN}'),
        (f"/api/runs/{rid}/tau", b'{"tau": Infinity}'),
        ("/api/runs", b'{"scene_id": "%s", "iterations": NaN}' % scene_id.encode()),
        (f"/api/runs/{rid}/exports", b'{"format": "splat", "exposure": NaN}'),
    ):
        r = client.post(path, content=body, headers=js)
        assert r.status_code == 422, (path, body, r.status_code)
        assert "finite" in r.text or "nan" in r.text.lower(), r.text
    assert client.post("/api/runs", json={"scene_id": scene_id, "seed": 10**30}).status_code == 422
    assert client.post("/api/runs", json={"scene_id": scene_id, "exposure": 1.5}).status_code == 422
    for times in ("0:1:100000000", "0:1:0", ",".join(["1"] * 4500), "0:2:3"):  # refused before a job starts
        r = client.post(f"/api/runs/{rid}/exports", json={"format": "splat", "times": times})
        assert r.status_code == 422 and "--times" in r.text, times[:20]
    r = client.post("/api/scenes", json={"source": "synth", "size": 1024, "frames": 2000, "subframes": 64})
    assert r.status_code == 422 and "subframes" in r.text
    big = b'{"tau": 1e-4, "pad": "' + b"x" * (2 << 20) + b'"}'
    assert client.post(f"/api/runs/{rid}/tau", content=big, headers=js).status_code == 413


def test_scene_with_runs_cannot_be_deleted_and_uploads_are_cleaned(client, tmp_path):
    rid = client.run_id
    scene_id = client.get(f"/api/runs/{rid}").json()["scene_id"]
    r = client.delete(f"/api/scenes/{scene_id}")
    assert r.status_code == 409 and rid in r.json()["detail"]
    assert client.get(f"/api/runs/{rid}/frames/0/image").status_code == 200  # the run still has its scene
    # An uploaded video whose ingest never produced a scene goes with the scene's row.
    ws = client.app_.state.ws
    row = ws.insert(
        "scenes", name="clip", path=str(ws.new_dir("scenes", "deadbeef0001")), source="ingest", status="failed", id="deadbeef0001"
    )
    video = ws.root / "scenes" / f".{row['id']}.video"
    video.write_bytes(b"\0" * 100)
    assert client.delete(f"/api/scenes/{row['id']}").status_code == 204 and not video.exists()
    # A failed ingest leaves no scene folder and keeps its uploaded copy for a retry.
    from kgs_backend.worker import run_ingest

    bogus = tmp_path / ".x.video"
    bogus.write_bytes(b"not a video")
    with pytest.raises(Exception, match="x.video"):
        run_ingest({"video": str(bogus), "out": str(tmp_path / "out"), "delete_video": True})
    assert bogus.exists() and not (tmp_path / "out").exists()


def test_a_cancel_the_ingest_swallowed_still_leaves_no_scene_and_keeps_the_videos(tmp_path, monkeypatch):
    """A SIGTERM whose exception is lost on the way (raised inside a callback from native code
    that carries on, or arriving as the ingest ends) still cancels: no scene, videos kept."""
    import os
    import signal

    import kgs_core.data.ingest as ingest_module
    from kgs_backend.worker import Cancelled, run_ingest

    def finishes_anyway(video, out, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # the handler raises Cancelled here...
            time.sleep(1.0)
        except Exception:
            pass  # ...and the native code it ran in swallows it and finishes
        Path(out).mkdir(parents=True)
        (Path(out) / "dataset.json").write_text("{}")

    monkeypatch.setattr(ingest_module, "ingest", finishes_anyway)
    videos = [tmp_path / ".s.video", tmp_path / ".s.sharp.video"]
    for v in videos:
        v.write_bytes(b"video")
    previous = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Cancelled):
        run_ingest({"video": str(videos[0]), "eval_video": str(videos[1]), "out": str(tmp_path / "out"), "delete_video": True})
    assert signal.getsignal(signal.SIGTERM) is previous
    assert all(v.exists() for v in videos) and not (tmp_path / "out").exists()


def test_video_upload_second_camera_stages_cancel_and_retry(client, room_video):
    """The UI's video flow through the API: upload held, a second camera's video, ingest with
    options, its stages as it runs, cancel (nothing half-made, the videos kept), retry to the end."""
    video, _ = room_video
    data, vt = Path(video).read_bytes(), {"content-type": "video/mp4"}
    up = client.post("/api/scenes/upload", params={"name": "room clip", "kind": "video", "hold": "true"}, content=data, headers=vt)
    assert up.status_code == 201, up.text
    assert up.json()["status"] == "uploaded" and up.json()["videos"] == 1
    sid = up.json()["id"]
    assert client.post(f"/api/scenes/{sid}/video", params={"role": "sharp"}, content=b"junk", headers=vt).status_code == 415
    r = client.post(f"/api/scenes/{sid}/video", params={"role": "sharp"}, content=data, headers=vt)
    assert r.status_code == 201 and r.json()["videos"] == 2
    for bad in ({"max_size": 10}, {"holdout_every": 1}, {"mapper": "magic"}, {"exposure": 2}, {"extra": 1}):
        assert client.post(f"/api/scenes/{sid}/ingest", json=bad).status_code == 422, bad
    assert client.post(f"/api/scenes/{sid}/cancel").status_code == 409  # nothing running yet
    # Start, see a stage reported, cancel: the scene is cancelled with nothing written.
    assert client.post(f"/api/scenes/{sid}/ingest", json={"max_size": 160}).status_code == 202
    deadline = time.time() + 60
    while not (client.get(f"/api/scenes/{sid}").json().get("progress") or {}).get("stage"):
        assert time.time() < deadline, "the ingest reported no stage"
        time.sleep(0.1)
    assert client.post(f"/api/scenes/{sid}/ingest", json={}).status_code == 409  # already running
    assert client.delete(f"/api/scenes/{sid}").status_code == 409
    assert client.post(f"/api/scenes/{sid}/cancel").status_code == 202
    st = wait_status(client, f"/api/scenes/{sid}", timeout=60)
    assert st["status"] == "cancelled" and st["videos"] == 2, st
    ws = client.app_.state.ws
    assert not Path(ws.get("scenes", sid)["path"]).exists()
    assert not [p.name for p in (ws.root / "scenes").iterdir() if p.name.startswith(f".{sid}.") and p.is_dir()]
    # Retry with the same videos, to the end: both cameras posed, every stage with its time.
    assert client.post(f"/api/scenes/{sid}/ingest", json={"max_size": 160}).status_code == 202
    done = wait_status(client, f"/api/scenes/{sid}", timeout=180)
    assert done["status"] == "done", done
    assert done["train_frames"] >= 14 and done["test_frames"] >= 14 and done["videos"] == 0
    stages = [name for name, _ in done["progress"]["stages"]] + [done["progress"]["stage"]]
    # (the stages name no file: the uploaded copy's name is the server's own)
    assert stages[0] == "decode" and "features" in stages and "matching" in stages, stages
    assert any(s.startswith("mapping") for s in stages) and stages[-1] == "undistort and write", stages
    assert client.post(f"/api/scenes/{sid}/ingest", json={}).status_code == 409  # no video waits any more


def test_registry_closes_its_connections(tmp_path, monkeypatch):
    """Every connection the registry opens is closed again (a connection's own `with` only
    commits: an outside probe saw 25 open handles after 900 requests)."""
    import sqlite3

    from kgs_backend import registry

    opened = []

    class Tracked(sqlite3.Connection):
        closed = False

        def close(self):
            self.closed = True
            super().close()

    real_connect = sqlite3.connect

    def connect(*args, **kwargs):
        db = real_connect(*args, factory=Tracked, **kwargs)
        opened.append(db)
        return db

    monkeypatch.setattr(registry.sqlite3, "connect", connect)
    ws = registry.Workspace(tmp_path / "ws")
    row = ws.insert("scenes", name="s", path=str(tmp_path / "s"), source="path", status="done")
    ws.update("scenes", row["id"], status="failed")
    assert ws.get("scenes", row["id"])["status"] == "failed" and len(ws.list("scenes")) == 1
    ws.delete("scenes", row["id"])
    assert len(opened) >= 5 and all(db.closed for db in opened)


def test_full_or_read_only_storage_is_named_not_a_500(client, monkeypatch):
    """A full disk answers 507 and a read-only workspace 503, each with a message that names
    the problem and no server path; other errors stay errors."""
    scene_id = client.get(f"/api/runs/{client.run_id}").json()["scene_id"]
    ws = client.app_.state.ws
    for exc, status, words in [
        (OSError(errno.ENOSPC, "No space left on device", str(ws.root / "runs")), 507, "disk is full"),
        (OSError(errno.EROFS, "Read-only file system", str(ws.root / "runs")), 503, "read-only"),
        (sqlite3.OperationalError("attempt to write a readonly database"), 503, "registry cannot be written"),
        (sqlite3.OperationalError("database or disk is full"), 507, "disk is full"),
    ]:

        def refuse(*a, _exc=exc, **k):
            raise _exc

        monkeypatch.setattr(ws, "new_dir", refuse)
        r = client.post("/api/runs", json={"scene_id": scene_id, "iterations": 10})
        assert r.status_code == status and words in r.json()["detail"], (exc, r.text)
        assert str(ws.root) not in r.text
    monkeypatch.setattr(ws, "new_dir", lambda *a, **k: (_ for _ in ()).throw(OSError(errno.EACCES, "denied")))
    with pytest.raises(PermissionError):
        client.post("/api/runs", json={"scene_id": scene_id, "iterations": 10})


def test_export_options_are_checked_before_a_job_and_a_video_follows_them(client, tmp_path):
    """Combinations the exporter refuses answer 422 naming the field; a video from one fixed
    view at a chosen size has that size and one frame a time; its job reported its stages."""
    import av

    rid = client.run_id
    vm = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3], [0, 0, 0, 1]]
    view = {"viewmat": vm, "fov_deg": 60, "width": 64, "height": 48}
    for body, word in (
        ({"format": "mp4", "camera_path": "view"}, "view"),
        ({"format": "mp4", "view": view}, "view"),
        ({"format": "mp4", "camera_path": "view", "view": {**view, "viewmat": [[2, 0, 0, 0]] * 4}}, "rotation"),
        ({"format": "mp4", "camera_path": "orbit", "side_by_side": True}, "side_by_side"),
        ({"format": "splat", "size": 256}, "size"),
        ({"format": "mp4", "size": 8}, "size"),
        ({"format": "glb", "web_frame": True}, "web_frame"),
        ({"format": "glb", "times": "0,1"}, "one time"),
    ):
        r = client.post(f"/api/runs/{rid}/exports", json=body)
        assert r.status_code == 422 and word in r.text, (body, r.text[:300])
    r = client.post(f"/api/runs/{rid}/exports", json={"format": "mp4", "camera_path": "view", "view": view, "size": 96, "times": "0:1:5"})
    assert r.status_code == 202, r.text
    e = wait_status(client, f"/api/exports/{r.json()['id']}")
    assert e["status"] == "done", e
    (tmp_path / "v.mp4").write_bytes(client.get(f"/api/exports/{e['id']}/download").content)
    with av.open(str(tmp_path / "v.mp4")) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert len(frames) == 5 and frames[0].shape == (72, 96, 3)
    progress = json.loads((client.app_.state.ws.root / "jobs" / f"{e['id']}.progress.json").read_text())
    assert progress["stage"] == "encode video" and progress["done"] == progress["total"] == 5
    assert [s[0] for s in progress["stages"]] == ["render video"]


def test_the_object_tool_selects_the_moving_gaussians_connected_to_one(client):
    """Every Gaussian the endpoint returns is dynamic, kept and joined to the clicked one (the
    same component `connected_object` finds); a static Gaussian or a bad index is refused."""
    from kgs_core.selection import connected_object, largest_sigma

    rid = client.run_id
    view = client.app_.state.views.get(rid, Path(client.app_.state.ws.get("runs", rid)["path"]))
    g, lod = view.baked(0.5, subset="dynamic")
    seed = int(g.index[0])
    r = client.post(f"/api/runs/{rid}/select-object", json={"index": seed, "t": 0.5})
    assert r.status_code == 200, r.text
    got = r.json()
    assert seed in got["indices"] and set(got["indices"]) <= set(g.index.tolist())
    expect = g.index[connected_object(g.means, largest_sigma(g.covars), 0)]
    assert sorted(got["indices"]) == sorted(expect.tolist())
    static, _ = view.baked(0.5, subset="static")
    r = client.post(f"/api/runs/{rid}/select-object", json={"index": int(static.index[0]), "t": 0.5})
    assert r.status_code == 422 and "moving" in r.text
    assert client.post(f"/api/runs/{rid}/select-object", json={"index": 0, "t": 2}).status_code == 422


def test_connected_object_follows_touching_gaussians_and_stops_at_empty_space():
    """Two clusters a gap apart and a chain of touching Gaussians between two others; a ball in
    front of a wall: a seed on the ball's front takes its back half, not the wall; a sparse
    object (large Gaussians far apart) stays whole."""
    from kgs_core.selection import connected_object, largest_sigma

    rng = np.random.default_rng(1)
    a, b = rng.uniform(0, 1, (400, 3)), rng.uniform(0, 1, (300, 3)) + [3, 0, 0]
    pts = np.concatenate([a, b])
    size = np.full(len(pts), 0.1)  # touching within 0.4: each cluster whole, the 2-unit gap not crossed
    assert connected_object(pts, size, 0).tolist() == list(range(400))
    assert connected_object(pts, size, 450).tolist() == list(range(400, 700))
    chain = np.stack([np.linspace(1, 3, 40), np.full(40, 0.5), np.full(40, 0.5)], 1)  # 0.05 apart
    assert len(connected_object(np.concatenate([pts, chain]), np.full(740, 0.1), 0)) == 740
    small_links = np.concatenate([size, np.full(40, 0.005)])  # the chain's Gaussians too small to touch
    assert len(connected_object(np.concatenate([pts, chain]), small_links, 0)) < 740
    with pytest.raises(ValueError, match="seed"):
        connected_object(pts, size, 700)
    d = rng.normal(size=(1500, 3))
    ball = 0.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    wall = np.stack([rng.uniform(-2, 2, 3000), rng.uniform(-2, 2, 3000), np.full(3000, 1.5)], 1)
    front = int(np.argmin(ball[:, 2]))  # nearest a camera looking along +z
    got = connected_object(np.concatenate([ball, wall]), np.full(4500, 0.02), front)
    assert got.tolist() == list(range(1500))
    sparse = np.stack([np.linspace(0, 1, 11), np.zeros(11), np.zeros(11)], 1)  # 0.1 apart, sigma 0.03
    assert len(connected_object(sparse, largest_sigma(np.tile(np.eye(3) * 0.03**2, (11, 1, 1))), 0)) == 11
