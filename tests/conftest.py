import json
import os
import urllib.request

import numpy as np
import pytest
import torch

# Tests must not depend on the developer's thread settings; two threads like CI.
torch.set_num_threads(min(2, os.cpu_count() or 1))


@pytest.fixture(autouse=True, scope="session")
def ingest_cache(tmp_path_factory):
    """Ingest's frame-set cache lives in a temporary folder, not in the user's home."""
    from kgs_core.render import _ext

    folder = tmp_path_factory.mktemp("kgs-cache")
    # The C++ rasteriser stays where README's set-up built it (servers started here never build).
    os.environ.setdefault("KGS_EXT_CACHE_DIR", str(_ext.ext_root()))
    old = os.environ.get("KGS_CACHE_DIR")
    os.environ["KGS_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("KGS_CACHE_DIR", None)
    else:
        os.environ["KGS_CACHE_DIR"] = old


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium (/usr/bin/chromium) with WebGL2 on SwiftShader, for the browser tests;
    those modules skip themselves when Chromium or Playwright is missing."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(
            executable_path="/usr/bin/chromium",
            args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"],
        )
        yield b
        b.close()


@pytest.fixture(scope="session")
def ext():
    """The compiled C++ rasteriser (built once per machine, then cached)."""
    from kgs_core.render import _ext

    return _ext.load()


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A small trained run (synthetic 'bounce', 48 px, 8 frames, 150 iterations, two LoD
    levels, decomposed) shared by the export, server and viewer tests. Read-only: tests that
    write edits copy it first (`copy_run`)."""
    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.train.config import make_config
    from kgs_core.train.trainer import train

    root = tmp_path_factory.mktemp("tiny_run")
    scene_dir = synthesize("bounce", root / "scenes" / "bounce", blur="mild", size=48, frames=8, subframes=4, progress=False)
    cfg = make_config(
        "fast",
        iterations=150,
        eval_every=50,
        checkpoint_every=1000,
        decompose_at=60,
        decompose_every=0,
        lod_fractions=(0.5, 1.0),
        lod_levels=2,
        lod_importance_views=2,
        init_points=1500,
        **{
            "densify.start": 30,
            "densify.every": 30,
            "densify.stop": 120,
            "densify.opacity_reset_at": (),
            "densify.max_gaussians": 4000,
            "model.tau": 5e-7,
        },
    )
    run_dir = root / "runs" / "bounce-tiny"
    train(load_scene(scene_dir), run_dir, cfg, progress=False)
    return run_dir


@pytest.fixture
def copy_run(tiny_run, tmp_path):
    """A private copy of `tiny_run` (with its scene) that a test may modify."""
    import shutil

    dst = tmp_path / "ws"
    shutil.copytree(tiny_run.parent.parent, dst)
    return dst / "runs" / tiny_run.name


@pytest.fixture(scope="session")
def room_video(tmp_path_factory):
    """A 16-frame, 160 px H.264 video of the synthetic textured 'room' (a moving camera, known
    poses), and that scene: what SfM can pose in seconds."""
    import numpy as np

    from kgs_core.data.formats import load_scene
    from kgs_core.data.synth.generate import synthesize
    from kgs_core.data.video import encode_video

    root = tmp_path_factory.mktemp("sfm")
    syn = synthesize("room", root / "room", blur="none", size=160, frames=16, progress=False)
    gt = load_scene(syn)
    frames = [(f.image() * 255).round().astype(np.uint8) for f in gt.train_frames]
    return encode_video(frames, root / "room.mp4", fps=12), gt


class RunsCode:
    """Unpickling this runs `open(path, "w")`: whether the marker file exists says whether a
    load ran code from a pickle."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


@pytest.fixture(scope="session")
def runs_code():
    return RunsCode


def write_colmap_text(scene_dir, root, first_image: str | None = None):
    """The scene in `scene_dir` as a COLMAP text model in `root` (images, times.json), its first
    image renamed `first_image` in images.txt and times.json when given (a hostile name)."""
    import json

    import pycolmap

    from kgs_core.data.formats import load_scene, write_colmap

    write_colmap(load_scene(scene_dir), root)
    model = root / "sparse" / "0"
    pycolmap.Reconstruction(str(model)).write_text(str(model))
    for name in ("cameras.bin", "images.bin", "points3D.bin", "frames.bin", "rigs.bin"):
        (model / name).unlink(missing_ok=True)
    if first_image is not None:
        lines = (model / "images.txt").read_text().splitlines()
        k = next(i for i, ln in enumerate(lines) if ln and not ln.startswith("#"))
        old = lines[k].split(" ")[-1]
        lines[k] = " ".join(lines[k].split(" ")[:-1] + [first_image])
        (model / "images.txt").write_text("\n".join(lines) + "\n")
        times = json.loads((root / "times.json").read_text())
        times[first_image] = times.pop(old)
        (root / "times.json").write_text(json.dumps(times))
    return root


@pytest.fixture(scope="session")
def colmap_text():
    return write_colmap_text


# ------------------------------------------------------------------ the browser viewer's tests


def require_browser() -> None:
    """At a browser test module's import: skip it without Chromium and Playwright, unless
    KGS_REQUIRE_BROWSER=1 (set by .ci/run), where a missing browser is a failure."""
    from pathlib import Path

    if not Path("/usr/bin/chromium").exists():
        if os.environ.get("KGS_REQUIRE_BROWSER") == "1":
            raise RuntimeError("KGS_REQUIRE_BROWSER=1 but /usr/bin/chromium is missing (apt-get install chromium)")
        pytest.skip("no /usr/bin/chromium (apt-get install chromium)", allow_module_level=True)
    pytest.importorskip("playwright.sync_api")


@pytest.fixture(scope="module")
def server(tiny_run, tmp_path_factory):
    import shutil

    from kgs_backend.launch import ServerProcess

    root = tmp_path_factory.mktemp("browser")
    shutil.copytree(tiny_run.parent.parent, root / "data")
    run = root / "data" / "runs" / tiny_run.name
    with ServerProcess([run], root / "ws") as srv:
        yield {"base": srv.base, "run_id": srv.runs[0]["id"], "run_dir": run}


@pytest.fixture
def page(browser, server):
    ctx = browser.new_context(viewport={"width": 900, "height": 600}, accept_downloads=True)
    page = ctx.new_page()
    errors = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.goto(f"{server['base']}/#/run/{server['run_id']}")
    page.wait_for_selector("body[data-ready='1']", timeout=60_000)
    meta = json.loads(urllib.request.urlopen(f"{server['base']}/api/runs/{server['run_id']}").read())
    f = meta["frames"][0]
    K = [v for row in f["K"] for v in row]
    page.evaluate("([vm, K, w, h]) => kgs.setCamera(vm, K, w, h)", [sum(f["viewmat"], []), K, f["width"], f["height"]])
    yield page
    assert not errors, errors
    ctx.close()


def pixels(page, t: float | None = None) -> np.ndarray:
    if t is not None:
        page.evaluate("(t) => kgs.setTime(t)", t)
    page.evaluate("kgs.drawn()")
    d = page.evaluate("kgs.readPixels()")
    return np.array(d["rgb"], dtype=np.float64).reshape(d["height"], d["width"], 3)


def shake_run(run_dir, w=(0.0, 0.0, 2.0), b=(3.0, 0.0, 0.0)) -> None:
    """Gives a copied run a learned camera shake (the same for every training frame), as a run
    trained with `--camera-blur learned` keeps it in run.json: strong enough to blur a 48 px
    frame by a few pixels at exposure 0.5."""
    from kgs_core.data.formats import load_scene
    from kgs_core.run import load_run, write_run_json

    run = load_run(run_dir)
    info, frames = run.info, load_scene(run.scene_path()).train_frames
    info["config"]["camera_blur"] = "learned"
    info["camera_motion"] = [{"t": f.time, "w": list(w), "b": list(b)} for f in sorted(frames, key=lambda f: f.time)]
    write_run_json(run_dir, info)
