"""The viewer's editor, export panel and view settings as a user drives them in headless
Chromium (SwiftShader WebGL2) against a real `kgs-app serve`: selection (all, invert, subtract,
a moving object by a click), the export panel's options, view-dependent colour, field of view,
background, screenshots, the time in seconds, and the view and time kept in the URL. Needs
/usr/bin/chromium, as test_browser.py."""

from __future__ import annotations

import io
import json
import urllib.request
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import pixels, require_browser
from PIL import Image

require_browser()


def count(page) -> int:
    return int(page.inner_text("#sel-count").split()[0].replace(",", ""))


def shown(page) -> int:
    return int(page.get_attribute("#counts", "data-dynamic")) + int(page.get_attribute("#counts", "data-static"))


def test_select_all_invert_subtract_and_escape(page):
    pixels(page, 0.5)
    page.click("#sel-all")
    total = shown(page)
    assert count(page) == total
    page.select_option("#tool", "box")
    front = page.evaluate("kgs.selectBox(12, 12, 36, 36)")  # replaces
    assert count(page) == front > 0
    page.click("#sel-invert")
    assert count(page) == total - front
    page.click("#sel-invert")
    assert count(page) == front
    # Subtract a box inside the first, up to the selection's median column (the mode menu, then
    # Alt on a drag does the same): what it takes is what it took inside the first box.
    columns = page.evaluate("""() => { const out = [];
        for (const set of [kgs.static, kgs.dynamic]) { if (!set) continue; const p = set.positions;
          for (let i = 0; i < set.count; i++) if (kgs.selected.has(set.index[i]))
            out.push(kgs.screenPoint([p[3*i], p[3*i+1], p[3*i+2]])[0]); }
        return out; }""")
    cut = sorted(columns)[len(columns) // 2]
    page.select_option("#sel-mode", "subtract")
    inner = page.evaluate(f"kgs.selectBox(12, 12, {cut}, 36)")
    assert 0 < inner < front and count(page) == front - inner
    page.select_option("#sel-mode", "replace")
    page.evaluate(f"kgs.selectBox(12, 12, {cut}, 36, 'add')")
    assert count(page) == front
    page.click("#canvas", position={"x": 5, "y": 5})  # the keyboard to the viewer (navigate tool: no selection change)
    page.keyboard.press("Control+a")
    assert count(page) == total
    page.keyboard.press("Escape")
    assert count(page) == 0
    page.keyboard.press("Control+i")
    assert count(page) == total
    page.keyboard.press("Escape")


def test_a_click_with_the_object_tool_takes_its_connected_moving_gaussians_and_delete_removes_them(page, server):
    """A click on a dynamic splat selects the component the server finds for it (the same for
    any of its members: what connects is symmetric), dynamic Gaussians only; Alt-click takes it
    away again; Delete removes exactly those, and undo brings them back. (That a component is the
    whole object, front and back, is tested on shapes in test_serve.py: this tiny run's dynamic
    set is too little trained to hold an object.)"""
    pixels(page, 0.5)
    dyn = page.evaluate("""() => { const d = kgs.dynamic, p = d.positions, out = [];
        for (let i = 0; i < d.count; i++) out.push([d.index[i], ...kgs.screenPoint([p[3*i], p[3*i+1], p[3*i+2]])]);
        return out; }""")
    w = page.evaluate("kgs.canvas.width")
    page.select_option("#tool", "object")
    # The first on-screen dynamic splat on the visible surface (one behind a static splat is not
    # what a click there shows).
    for index, u, v, z in dyn:
        if 4 < u < w - 4 and 4 < v < w - 4 and z > 0:
            n = page.evaluate(f"kgs.selectObjectAt({u}, {v})")
            if n:
                break
    assert n >= 1 and count(page) == n
    selected = sorted(page.evaluate("[...kgs.selected]"))
    assert set(selected) <= {h[0] for h in dyn}, "the object tool took a static Gaussian"
    again = json.loads(
        urllib.request.urlopen(
            urllib.request.Request(
                f"{server['base']}/api/runs/{server['run_id']}/select-object",
                method="POST",
                data=json.dumps({"index": selected[-1], "t": 0.5}).encode(),
                headers={"content-type": "application/json"},
            )
        ).read()
    )
    assert sorted(again["indices"]) == selected
    # A real click on the canvas, with Alt: the same object taken out of the selection.
    box = page.locator("#canvas").bounding_box()
    scale = box["width"] / w
    page.keyboard.down("Alt")
    page.mouse.click(box["x"] + u * scale, box["y"] + v * scale)
    page.keyboard.up("Alt")
    page.wait_for_function("document.querySelector('#sel-count').textContent.startsWith('0 ')", timeout=30_000)
    page.evaluate(f"kgs.selectObjectAt({u}, {v})")
    dynamic_before = int(page.get_attribute("#counts", "data-dynamic"))
    page.keyboard.press("Delete")
    page.wait_for_function(f"+document.querySelector('#counts').dataset.dynamic == {dynamic_before - n}", timeout=30_000)
    page.click("#edit-undo")
    page.wait_for_function(f"+document.querySelector('#counts').dataset.dynamic == {dynamic_before}", timeout=30_000)


def download(page) -> bytes:
    page.wait_for_selector("#export-link", timeout=120_000)
    with page.expect_download() as dl:
        page.click("#export-link")
    return Path(dl.value.path()).read_bytes()


def test_export_panel_options_reach_the_files(page, server, tmp_path):
    """A video from this view at 256 px; .splat files for a range of frames, framed for the web
    viewers (export.json says so), named after the run; the panel shows the job's stages."""
    import av

    pixels(page, 0.5)
    page.select_option("#export-format", "mp4")
    assert page.is_visible("#export-path") and not page.is_visible("#export-web")
    page.select_option("#export-path", "view")
    assert page.is_disabled("#export-side")
    page.select_option("#export-size", "256")
    page.click("#export-go")
    page.wait_for_selector("#export-link", timeout=120_000)
    (tmp_path / "v.mp4").write_bytes(download(page))
    with av.open(str(tmp_path / "v.mp4")) as c:
        frames = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    assert frames[0].shape == (256, 256, 3) and len(frames) == 60  # the canvas is square in this test
    page.select_option("#export-format", "splat")
    assert page.input_value("#export-times") == "now" and page.is_checked("#export-web")
    page.select_option("#export-times", "range")
    page.fill("#export-from", "2")
    page.fill("#export-to", "4")
    page.click("#export-go")
    data = download(page)
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        names = sorted(z.namelist())
        report = json.loads(z.read("export.json"))
    assert names == ["cameras.json", "export.json", "frame_00000.splat", "frame_00001.splat", "frame_00002.splat"]
    meta = json.loads(urllib.request.urlopen(f"{server['base']}/api/runs/{server['run_id']}").read())
    times = sorted({f["time"] for f in meta["frames"] if f["split"] == "train" and not f.get("camera_id")})
    assert [round(f["time"], 5) for f in report["frames"]] == [round(t, 5) for t in times[1:4]]
    assert report["web_frame"]["viewer"] == "antimatter15/splat"


def open_viewer(browser, base: str, run_id: str, query: str = "", **context):
    ctx = browser.new_context(viewport={"width": 700, "height": 500}, accept_downloads=True, **context)
    page = ctx.new_page()
    page.goto(f"{base}/#/run/{run_id}{query}")
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    page.evaluate("kgs.drawn()")
    return ctx, page


def read(page) -> np.ndarray:
    page.evaluate("kgs.drawn()")
    d = page.evaluate("kgs.readPixels()")
    return np.array(d["rgb"], dtype=np.float64).reshape(d["height"], d["width"], 3)


@pytest.fixture(scope="module")
def sh_server(tiny_run, tmp_path_factory):
    """The test run with strong view-dependent colour: its SH coefficients after the DC term
    (every LoD level's) replaced by random ones, so that leaving them out shows."""
    import shutil

    import torch

    from kgs_backend.launch import ServerProcess
    from kgs_core.run import load_torch, save_torch

    root = tmp_path_factory.mktemp("sh")
    shutil.copytree(tiny_run.parent.parent, root / "data")
    run = root / "data" / "runs" / tiny_run.name
    state = load_torch(run / "model.pt")
    gen = torch.Generator().manual_seed(0)
    for params in [state["model"]["params"], *(lvl["params"] for lvl in state["levels"])]:
        params["sh_rest"] = 0.5 * torch.randn(params["sh_rest"].shape, generator=gen)
    save_torch(run / "model.pt", state)
    with ServerProcess([run], root / "ws") as srv:
        yield {"base": srv.base, "run_id": srv.runs[0]["id"]}


def test_view_dependent_colour_matches_the_cpu_rasteriser(browser, sh_server):
    """With strong SH terms the browser's frame matches the server's full-SH render from the
    training camera; drawn with the base colour only it does not (a wrong basis sign fails)."""
    base, rid = sh_server["base"], sh_server["run_id"]
    ctx, page = open_viewer(browser, base, rid)
    meta = json.loads(urllib.request.urlopen(f"{base}/api/runs/{rid}").read())
    f = meta["frames"][0]
    page.evaluate("([vm, K, w, h]) => kgs.setCamera(vm, K, w, h)", [sum(f["viewmat"], []), sum(f["K"], []), f["width"], f["height"]])
    page.evaluate("kgs.setTime(0.5)")
    web = read(page)
    png = urllib.request.urlopen(f"{base}/api/runs/{rid}/render?t=0.5&frame=0").read()
    cpu = np.asarray(Image.open(io.BytesIO(png)), dtype=np.float64)
    page.uncheck("#view-sh")
    flat = read(page)
    ctx.close()
    err, err_flat = np.abs(web - cpu).mean(), np.abs(flat - cpu).mean()
    print(f"browser vs CPU with SH: {err:.2f}/255, base colour only: {err_flat:.2f}/255")
    assert err < 6.0 and err_flat > 2 * err


def test_field_of_view_background_and_screenshot(browser, server):
    ctx, page = open_viewer(browser, server["base"], server["run_id"])
    w = page.evaluate("kgs.canvas.width")
    before = read(page)
    page.fill("#fov", "30")
    page.dispatch_event("#fov", "input")
    fx = page.evaluate("kgs.intrinsics()[0]")
    assert fx == pytest.approx(w / (2 * np.tan(np.radians(15))), rel=1e-6)
    assert page.inner_text("#fov-label") == "30°" and np.abs(read(page) - before).mean() > 1
    page.click("#reset-view")
    assert np.abs(read(page) - before).max() == 0
    # Background: C + (1 - A) bg, so red where the splats do not cover, the other channels alike.
    page.eval_on_selector("#background", "(el) => { el.value = '#ff0000'; el.dispatchEvent(new Event('input')); }")
    red = read(page)
    assert np.abs(red[..., 1:] - before[..., 1:]).max() <= 1
    assert (red[..., 0] >= before[..., 0] - 1).all() and (red[..., 0] - before[..., 0]).max() > 20
    with page.expect_download() as dl:
        page.click("#screenshot")
    assert dl.value.suggested_filename == "bounce-tiny-frame1.png"
    shot = np.asarray(Image.open(dl.value.path()).convert("RGB"), dtype=np.float64)
    assert shot.shape == red.shape and np.abs(shot - red).max() <= 1
    ctx.close()


def test_the_url_keeps_the_view_and_time_and_the_label_reads_seconds(browser, server):
    """Step two frames and turn the view: the URL says so, a reload shows the same picture, and
    the link opened elsewhere too. The time label names the frame and its second (the synthetic
    camera films at 30 frames a second)."""
    ctx, page = open_viewer(browser, server["base"], server["run_id"])
    assert page.inner_text("#time-label").startswith("frame 1 of 8 · 0.00 s · t = 0.000")
    page.click("#canvas")
    page.keyboard.press("ArrowRight")
    page.keyboard.press("ArrowRight")
    assert page.inner_text("#time-label").startswith("frame 3 of 8 · 0.07 s · t = ")
    box = page.locator("#canvas").bounding_box()
    page.mouse.move(box["x"] + 200, box["y"] + 200)
    page.mouse.down()
    page.mouse.move(box["x"] + 260, box["y"] + 180, steps=5)
    page.mouse.up()
    page.wait_for_timeout(800)  # the URL follows the view at most every 300 ms: let it settle on the last move
    page.wait_for_function("location.hash.includes('orbit=') && location.hash.includes('t=0.285714')", timeout=5_000)
    picture = read(page)
    url = page.url
    page.reload()
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    assert page.inner_text("#time-label").startswith("frame 3 of 8")
    assert np.abs(read(page) - picture).mean() < 0.5
    # Playback past the end shows the last frame, then loops to the first.
    page.evaluate("kgs.setTime(0.99); kgs.advancePlayback(0.1)")
    assert page.evaluate("kgs.t") == 1 and page.inner_text("#time-label").startswith("frame 8 of 8")
    page.evaluate("kgs.advancePlayback(0.1)")
    assert page.evaluate("kgs.t") == 0
    ctx.close()
    ctx, page = open_viewer(browser, server["base"], server["run_id"], "?" + url.split("?", 1)[1])
    assert np.abs(read(page) - picture).mean() < 0.5
    ctx.close()


def drop_file(page, path: Path) -> None:
    """What the browser does when a file is dragged from the desktop onto the page."""
    import base64

    page.evaluate(
        """([name, b64]) => {
        const bytes = Uint8Array.from(atob(b64), (c) => c.charCodeAt(0));
        const dt = new DataTransfer();
        dt.items.add(new File([bytes], name));
        window.dispatchEvent(new DragEvent("drop", { dataTransfer: dt, bubbles: true, cancelable: true }));
    }""",
        [path.name, base64.b64encode(path.read_bytes()).decode()],
    )


@pytest.mark.parametrize("fmt", ["ply-seq", "splat"])
def test_a_dropped_file_draws_as_the_run_does(browser, server, tiny_run, tmp_path, fmt):
    """Our own export at t = 0.5, dropped on the runs page: the viewer opens it (count in the
    title, the run's controls off) and, from the run's first training camera, draws what the run's
    viewer draws at t = 0.5 (a .splat holds the base colour only, so the run is drawn so too)."""
    from kgs_core.export import export_run

    res = export_run(tiny_run, fmt, out=tmp_path / fmt, times="0.5", progress=False, web_frame=False)
    file = res.files[0].with_name("scene" + res.files[0].suffix)
    res.files[0].rename(file)
    meta = json.loads(urllib.request.urlopen(f"{server['base']}/api/runs/{server['run_id']}").read())
    f = meta["frames"][0]
    camera = [sum(f["viewmat"], []), sum(f["K"], []), f["width"], f["height"]]
    ctx, page = open_viewer(browser, server["base"], server["run_id"])
    page.evaluate("([vm, K, w, h]) => kgs.setCamera(vm, K, w, h)", camera)
    page.evaluate("kgs.setTime(0.5)")
    if fmt == "splat":
        page.uncheck("#view-sh")
    run_picture = read(page)
    ctx.close()
    ctx = browser.new_context(viewport={"width": 700, "height": 500})
    page = ctx.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{server['base']}/")
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    drop_file(page, file)
    page.wait_for_function("document.body.dataset.page === 'viewer' && document.body.dataset.ready === '1'", timeout=30_000)
    assert "(a local file)" in page.inner_text("#run-title") and page.is_disabled("#edit-delete")
    page.evaluate("([vm, K, w, h]) => kgs.setCamera(vm, K, w, h)", camera)
    local = read(page)
    err = np.abs(local - run_picture).mean()
    print(f"dropped {file.name} vs the run at t = 0.5: {err:.2f}/255")
    assert run_picture.std() > 5 and err < 2.0
    # A file that is not a splat file: the page says why and stays as it was.
    bad = tmp_path / "notes.ply"
    bad.write_text("hello")
    drop_file(page, bad)
    page.wait_for_function("document.querySelector('#status').textContent.includes('not a .ply file')", timeout=10_000)
    assert not errors, errors
    ctx.close()


def test_runs_page_thumbnails_labels_and_a_phone_sized_layout(browser, server):
    """The runs page: each finished run has a thumbnail (a real picture of it) and labelled
    figures; at 390 px wide the viewer's canvas takes the width, the controls below it."""
    ctx = browser.new_context(viewport={"width": 390, "height": 844}, device_scale_factor=1)
    page = ctx.new_page()
    page.goto(f"{server['base']}/")
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    page.wait_for_function(
        "(() => { const i = document.querySelector('#run-list img.thumb'); return i && i.complete && i.naturalWidth > 0; })()",
        timeout=60_000,
    )
    size = page.eval_on_selector("#run-list img.thumb", "i => [i.naturalWidth, i.naturalHeight]")
    assert max(size) == 48  # the long side at most 160 px, and this run's 48 px frames not upscaled
    item = page.inner_text(f"#run-list li[data-run='{server['run_id']}']")
    assert "scene " in item and "started " in item and "Gaussians" in item and "training" in item
    thumb = page.evaluate("""async () => { const i = document.querySelector('#run-list img.thumb');
        const c = document.createElement('canvas'); c.width = i.naturalWidth; c.height = i.naturalHeight;
        const g = c.getContext('2d'); g.drawImage(i, 0, 0);
        return Array.from(g.getImageData(0, 0, c.width, c.height).data); }""")
    assert np.asarray(thumb, dtype=float).reshape(-1, 4)[:, :3].std() > 5  # a picture, not a blank
    page.click(f"#run-list li[data-run='{server['run_id']}'] a")
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    canvas = page.locator("#canvas").bounding_box()
    controls = page.locator("#controls").bounding_box()
    assert canvas["width"] >= 370 and canvas["height"] >= 300, canvas
    assert controls["y"] >= canvas["y"] + canvas["height"] - 1 and controls["width"] >= 370
    ctx.close()
