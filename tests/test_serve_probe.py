"""The second outside probe of `kgs-app serve`: each finding's request, answered with a 4xx (or
running no code and reading no file), and the server's jobs bounded, queued and cleaned up."""

from __future__ import annotations

import io
import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from fastapi import HTTPException
from fastapi.testclient import TestClient
from PIL import Image

from kgs_backend.main import create_app
from kgs_backend.settings import Settings

BASE = "http://127.0.0.1:8000"


@pytest.fixture
def client(tmp_path, copy_run):
    app = create_app(Settings(workspace=tmp_path / "workspace", register=[copy_run], max_upload_mb=2))
    with TestClient(app, base_url=BASE) as c:
        c.run_id = app.state.registered[0]
        c.app_ = app
        c.ws = app.state.ws
        c.scene_id = c.get(f"/api/runs/{c.run_id}").json()["scene_id"]
        yield c


@pytest.fixture
def inside(copy_run):
    """A server whose workspace holds the run and its scene (as `kgs-app demo` leaves them)."""
    app = create_app(Settings(workspace=copy_run.parent.parent))
    with TestClient(app, base_url=BASE) as c:
        c.app_, c.ws = app, app.state.ws
        c.run_id = app.state.ws.list("runs")[0]["id"]
        c.scene_id = c.get(f"/api/runs/{c.run_id}").json()["scene_id"]
        yield c


def wait_status(c, path: str, done=("done", "failed", "cancelled", "interrupted"), timeout=240) -> dict:
    deadline = time.time() + timeout
    while time.time() < deadline:
        row = c.get(path).json()
        if row["status"] in done:
            return row
        time.sleep(0.3)
    raise AssertionError(f"{path} still {row['status']} after {timeout} s")


def zipped(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, data in files.items():
            z.writestr(name, data)
    return buf.getvalue()


def zip_folder(folder: Path, prefix: str = "data") -> dict[str, bytes]:
    return {f"{prefix}/{p.relative_to(folder)}": p.read_bytes() for p in folder.rglob("*") if p.is_file()}


ZIP = {"content-type": "application/zip"}


# ---------------------------------------------------------------- 1. code execution


def test_a_training_request_cannot_name_a_path_and_a_pickled_parent_runs_nothing(client, tmp_path, runs_code):
    RunsCode = runs_code
    marker = tmp_path / "code-ran"
    evil = tmp_path / "evil"
    evil.mkdir()
    (evil / "run.json").write_text(json.dumps({"format_version": 1, "status": "done", "config": {}}))
    torch.save({"model": RunsCode(marker)}, evil / "model.pt")
    for settings in (["init_from=" + str(evil)], ["init_from=" + str(evil) + "/"]):
        r = client.post("/api/runs", json={"scene_id": client.scene_id, "settings": settings})
        assert r.status_code == 422 and "init_from" in r.text, r.text
    r = client.post("/api/runs", json={"scene_id": client.scene_id, "init_from": str(evil)})
    assert r.status_code == 422  # not a field of the body
    # The same zip the probe uploaded: not a dataset, refused, and nothing of it is kept.
    r = client.post(
        "/api/scenes/upload",
        params={"name": "evil", "kind": "zip"},
        headers=ZIP,
        content=zipped({"evil/run.json": (evil / "run.json").read_bytes(), "evil/model.pt": (evil / "model.pt").read_bytes()}),
    )
    assert r.status_code == 422 and str(client.ws.root) not in r.text
    # Its parent by id: a run of this workspace, or a 404; never a path.
    assert client.post("/api/runs", json={"scene_id": client.scene_id, "init_from_run": "../../etc"}).status_code == 422
    assert client.post("/api/runs", json={"scene_id": client.scene_id, "init_from_run": "0123456789ab"}).status_code == 404
    # A parent whose model.pt was replaced by a pickle: the job fails to load it and runs nothing.
    parent = Path(client.ws.get("runs", client.run_id)["path"])
    torch.save({"model": RunsCode(marker), "levels": []}, parent / "model.pt")
    r = client.post("/api/runs", json={"scene_id": client.scene_id, "init_from_run": client.run_id, "iterations": 3})
    assert r.status_code == 202, r.text
    done = wait_status(client, f"/api/runs/{r.json()['id']}", timeout=120)
    assert done["status"] == "failed" and "model.pt: cannot load" in done["error"], done
    assert not marker.exists(), "a pickle in a run folder ran code on the server"


def test_a_training_request_starts_from_a_parent_run_by_id(client):
    r = client.post("/api/runs", json={"scene_id": client.scene_id, "init_from_run": client.run_id, "iterations": 3})
    assert r.status_code == 202, r.text
    done = wait_status(client, f"/api/runs/{r.json()['id']}", timeout=120)
    assert done["status"] == "done", done
    info = json.loads((Path(client.ws.get("runs", done["id"])["path"]) / "run.json").read_text())
    assert Path(info["config"]["init_from"]) == Path(client.ws.get("runs", client.run_id)["path"])


# ---------------------------------------------------------------- 2. a dataset reading any file


def colmap_zip(colmap_text, tmp_path: Path, tiny_run: Path, image_name: str) -> bytes:
    """The tiny run's scene as a zipped COLMAP text model whose first image is `image_name`."""
    return zipped(zip_folder(colmap_text(tiny_run.parent.parent / "scenes" / "bounce", tmp_path / "colmap", image_name)))


@pytest.mark.parametrize("name", ["ABSOLUTE", "../../../../../../../../SECRET", "../images/../../x.png"])
def test_a_colmap_upload_cannot_name_a_file_outside_it(client, tiny_run, tmp_path, name, colmap_text):
    secret = tmp_path / "secret.png"
    Image.fromarray(np.full((8, 8, 3), 200, np.uint8)).save(secret)
    name = str(secret) if name == "ABSOLUTE" else name.replace("SECRET", str(secret).lstrip("/"))
    r = client.post(
        "/api/scenes/upload", params={"name": "c", "kind": "zip"}, headers=ZIP, content=colmap_zip(colmap_text, tmp_path, tiny_run, name)
    )
    assert r.status_code == 422 and ("leaves the dataset folder" in r.text or "absolute path" in r.text), r.text
    assert str(client.ws.root) not in r.text and ".upload-" not in r.text
    # The answer is the same whether the file exists: it tells nothing about the server's disk.
    secret.unlink()
    again = client.post(
        "/api/scenes/upload",
        params={"name": "c", "kind": "zip"},
        headers=ZIP,
        content=colmap_zip(colmap_text, tmp_path / "again", tiny_run, name),
    )
    assert again.status_code == 422 and again.json() == r.json()


# ---------------------------------------------------------------- 3. unbounded jobs


def test_jobs_beyond_the_cores_wait_in_a_queue_with_their_position(client):
    jr = client.app_.state.jobs
    jr.max_jobs = 1
    body = {"source": "synth", "name": "bounce", "size": 32, "frames": 4, "subframes": 1}
    first, second, third = (client.post("/api/scenes", json=body).json() for _ in range(3))
    assert first["status"] == "running" and first["queue_position"] is None
    assert second["status"] == "queued" and second["queue_position"] == 1, second
    assert client.get(f"/api/scenes/{third['id']}").json()["queue_position"] == 2
    assert client.post(f"/api/scenes/{second['id']}/cancel").json()["status"] == "cancelled"
    assert client.get(f"/api/scenes/{third['id']}").json()["queue_position"] == 1
    assert wait_status(client, f"/api/scenes/{first['id']}")["status"] == "done"
    assert wait_status(client, f"/api/scenes/{third['id']}")["status"] == "done"
    assert client.get(f"/api/scenes/{second['id']}").json()["status"] == "cancelled"


def test_one_request_cannot_ask_for_a_machine(client):
    client.app_.state.jobs.start = lambda *a, **k: None  # (were a bound to fail, no job would run for hours)
    r = client.post("/api/scenes", json={"source": "synth", "size": 1024, "frames": 2000, "subframes": 1})
    assert r.status_code == 422 and "size² x frames" in r.text
    for body in (
        {"iterations": 1_000_001},
        {"settings": ["iterations=99999999999"]},
        {"settings": ["init_points=2000000000"]},
        {"settings": ["batch_size=100000"]},
        {"settings": ["model.deform_spatial=100000"]},
    ):
        r = client.post("/api/runs", json={"scene_id": client.scene_id, **body})
        assert r.status_code == 422, (body, r.text)
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    assert schema["TrainRequest"]["properties"]["iterations"]["anyOf"][0]["maximum"] == 1_000_000
    assert "2^27" in schema["SynthRequest"]["description"]


# ---------------------------------------------------------------- 4. huge images


def huge_png() -> bytes:
    """An 8000 x 8000 PNG of a few hundred KB: 192 MB once decoded."""
    buf = io.BytesIO()
    Image.new("L", (8000, 8000)).save(buf, format="PNG", optimize=True)
    return buf.getvalue()


def test_huge_images_are_refused_before_they_are_decoded(client, tmp_path):
    from kgs_core.data.formats import load_scene

    blob = huge_png()
    assert len(blob) < 2 * 1024 * 1024
    folder = Path(client.ws.get("scenes", client.scene_id)["path"])
    frame = load_scene(folder).frames[0]
    files = {k: v for k, v in zip_folder(folder).items() if "/sharp/" not in k and "/mask/" not in k and "/motion/" not in k}
    files[f"data/{Path(frame.image_path).relative_to(folder.resolve())}"] = blob
    r = client.post("/api/scenes/upload", params={"name": "huge", "kind": "zip"}, headers=ZIP, content=zipped(files))
    assert r.status_code == 413 and "8000x8000" in r.text, r.text
    # A scene on disk with such a frame: its image is a 409, not a decode.
    Path(frame.image_path).write_bytes(blob)
    r = client.get(f"/api/runs/{client.run_id}/frames/0/image")
    assert r.status_code == 409 and "8000x8000" in r.text and str(client.ws.root) not in r.text, r.text
    r = client.get(f"/api/runs/{client.run_id}/render", params={"width": 4096, "height": 4096})
    assert r.status_code == 422 and "pixels" in r.text
    assert client.get(f"/api/runs/{client.run_id}/render", params={"width": 64, "height": 48}).status_code == 200


# ---------------------------------------------------------------- 5. the C++ extension


def test_the_server_never_builds_the_extension(tmp_path):
    env = {**os.environ, "KGS_EXT_CACHE_DIR": str(tmp_path / "no-build-here"), "KGS_CACHE_DIR": str(tmp_path / "c")}
    t0 = time.time()
    r = subprocess.run(
        [sys.executable, "-m", "kgs_app.cli", "serve", "--workspace", str(tmp_path / "ws"), "--port", "9"],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert r.returncode != 0 and "kgs-app build-ext" in r.stderr, r.stderr
    assert time.time() - t0 < 60 and not list((tmp_path / "no-build-here").rglob("*.o"))


def test_a_finished_build_loads_without_the_build_tool(monkeypatch):
    from torch.utils import cpp_extension

    from kgs_core.render import _ext

    _ext.load()
    assert _ext.built()

    def no_ninja(*a, **k):
        raise AssertionError("a finished build ran the build tool again")

    monkeypatch.setattr(cpp_extension, "load", no_ninja)
    monkeypatch.setattr(_ext, "_module", None)
    assert _ext.load().simd_path()


# ---------------------------------------------------------------- 6.-7. settings and hostile metadata


@pytest.mark.parametrize(
    "setting", ["lr_means=NaN", "model.tau=Infinity", "seed=-5", "iterations=99999999999", "init_points=2000000000", "batch_size=100000"]
)
def test_settings_get_the_bounds_named_fields_get(client, setting):
    r = client.post("/api/runs", json={"scene_id": client.scene_id, "settings": [setting]})
    assert r.status_code == 422 and setting.split("=")[0] in r.text, r.text


@pytest.mark.parametrize("edit", ["camera_id null", "time list", "time NaN", "kgs.json list", "lying zip"])
def test_hostile_dataset_metadata_gets_a_4xx(client, tiny_run, tmp_path, edit):
    from kgs_core.data.formats import load_scene, write_colmap

    root = tmp_path / "c"
    write_colmap(load_scene(tiny_run.parent.parent / "scenes" / "bounce"), root)
    times = json.loads((root / "times.json").read_text())
    first = next(iter(times))
    if edit == "camera_id null":
        times[first]["camera_id"] = None
    elif edit == "time list":
        times[first]["time"] = [0.5]
    elif edit == "time NaN":
        times[first]["time"] = float("nan")
    elif edit == "kgs.json list":
        (root / "kgs.json").write_text("[]")
    (root / "times.json").write_text(json.dumps(times))
    blob = zipped(zip_folder(root))
    if edit == "lying zip":  # the central directory says the first entry is one byte
        data = bytearray(blob)
        k = data.index(b"PK\x01\x02")
        data[k + 24 : k + 28] = (1).to_bytes(4, "little")
        blob = bytes(data)
    r = client.post("/api/scenes/upload", params={"name": "c", "kind": "zip"}, headers=ZIP, content=blob)
    assert 400 <= r.status_code < 500, (edit, r.status_code, r.text)
    assert not [p for p in (client.ws.root / "scenes").iterdir() if p.name.startswith(".upload")]


# ---------------------------------------------------------------- 8.-11. jobs and rows


def test_a_killed_job_leaves_no_temporary_files(client):
    """SfM's glog ends the process on SIGTERM before Python unwinds: whatever a job had in its
    temporary folder goes once its process is gone, however it ended."""
    body = {"source": "synth", "name": "sheet", "size": 128, "frames": 60, "subframes": 16}
    sid = client.post("/api/scenes", json=body).json()["id"]
    pid = client.ws.get("scenes", sid)["pid"]
    environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    tmp = client.app_.state.jobs.tmp_dir(sid)
    assert f"TMPDIR={tmp}".encode() in environ
    (tmp / "kgs-sfm-leftover").mkdir()
    os.kill(pid, signal.SIGKILL)  # as an end that runs no Python
    wait_status(client, f"/api/scenes/{sid}")
    deadline = time.time() + 10
    while tmp.exists() and time.time() < deadline:
        time.sleep(0.1)
    assert not tmp.exists()


def test_a_stored_pid_of_another_process_is_never_signalled(client):
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        ws = client.ws
        ws.update("runs", client.run_id, status="running", pid=other.pid)
        assert client.post(f"/api/runs/{client.run_id}/cancel").status_code == 409
        client.app_.state.jobs.recover()  # as after a restart
        assert ws.get("runs", client.run_id)["status"] == "interrupted"
        assert other.poll() is None, "cancel signalled a process that was not the job's"
    finally:
        other.kill()
        other.wait()


def test_two_requests_racing_to_start_one_ingest_start_one_job(client, room_video):
    from kgs_backend.routers.scenes import IngestRequest, start_ingest

    data = Path(room_video[0]).read_bytes()
    sid = client.post(
        "/api/scenes/upload", params={"name": "clip", "kind": "video", "hold": "true"}, content=data, headers={"content-type": "video/mp4"}
    ).json()["id"]
    row = client.ws.get("scenes", sid)  # what both requests read before either starts the job
    jr = client.app_.state.jobs
    started = []
    real_start = jr.start
    jr.start = lambda *a, **k: started.append(a[1]) or real_start(*a, **k)
    start_ingest(client.ws, jr, row, IngestRequest(max_size=96))
    with pytest.raises(HTTPException) as second:
        start_ingest(client.ws, jr, row, IngestRequest(max_size=96))
    assert second.value.status_code == 409 and started == [sid]
    client.post(f"/api/scenes/{sid}/cancel")
    wait_status(client, f"/api/scenes/{sid}", timeout=60)


def test_a_delete_the_disk_refuses_deletes_nothing(inside, monkeypatch):
    client = inside
    ws = client.ws
    folder = Path(ws.get("runs", client.run_id)["path"])
    real = ws._connect

    def full(*a, **k):
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(ws, "remove", lambda rows, files=(), _r=ws.remove: (monkeypatch.setattr(ws, "_connect", full), _r(rows, files)))
    r = client.delete(f"/api/runs/{client.run_id}")
    monkeypatch.setattr(ws, "_connect", real)
    assert r.status_code == 507, r.text
    assert (folder / "model.pt").is_file() and ws.get("runs", client.run_id)["status"] == "done"
    assert not [p for p in folder.parent.iterdir() if p.name.startswith(".deleting-")]
    monkeypatch.undo()
    assert client.delete(f"/api/runs/{client.run_id}").status_code == 204 and not folder.exists()


# ---------------------------------------------------------------- 12.-14.


def test_answers_name_no_server_path_and_a_missing_scene_is_a_409(inside):
    client = inside
    scene = Path(client.ws.get("scenes", client.scene_id)["path"])
    (scene / "dataset.json").write_text("{")  # (deleted, the run would find the scene it was copied from)
    for path in (f"/api/runs/{client.run_id}/render", f"/api/runs/{client.run_id}/frames/0/image"):
        r = client.get(path)
        assert r.status_code == 409, (path, r.status_code, r.text)
        assert str(client.ws.root) not in r.text and str(client.ws.root.resolve()) not in r.text, r.text
    detail = client.get(f"/api/scenes/{client.scene_id}").json()
    assert str(client.ws.root) not in json.dumps(detail)


def test_a_zip_upload_is_never_read_whole_into_memory(client, tiny_run, monkeypatch):
    folder = tiny_run.parent.parent / "scenes" / "bounce"
    files = {k: v for k, v in zip_folder(folder).items() if "/sharp/" not in k and "/mask/" not in k and "/motion/" not in k}
    real = Path.read_bytes

    def guarded(self):
        assert self.name != "upload.zip", "the upload was read whole"
        return real(self)

    monkeypatch.setattr(Path, "read_bytes", guarded)
    r = client.post("/api/scenes/upload", params={"name": "ok", "kind": "zip"}, headers=ZIP, content=zipped(files))
    assert r.status_code == 201, r.text


def test_a_second_camera_video_over_a_mebibyte_uploads(client, room_video):
    """The second camera's upload is streamed under the upload limit, not the JSON body cap."""
    data = Path(room_video[0]).read_bytes()
    vt = {"content-type": "video/mp4"}
    sid = client.post("/api/scenes/upload", params={"name": "clip", "kind": "video", "hold": "true"}, content=data, headers=vt).json()["id"]
    padded = data + b"\0" * ((1 << 20) + 1024 - len(data))  # an mp4 reader ignores trailing bytes
    r = client.post(f"/api/scenes/{sid}/video", params={"role": "sharp"}, content=padded, headers=vt)
    assert r.status_code == 201 and r.json()["videos"] == 2, r.text
