"""The desktop viewer: moderngl on a headless EGL context (Mesa) against the CPU rasteriser,
the imgui controls driven headlessly (a real imgui context fed mouse events), the window under
xvfb-run, and a run viewed through a running server."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

moderngl = pytest.importorskip("moderngl")
imgui_bundle = pytest.importorskip("imgui_bundle")

# Mean absolute difference (8-bit levels) allowed between the GL frame and the CPU
# rasteriser's image of the same camera and time; measured 2.18 on the test run (SH DC colour
# only in GL, no early stop at T < 1e-4).
MAX_MEAN_ERROR = 6.0


@pytest.fixture(scope="module")
def egl():
    try:
        return moderngl.create_standalone_context(backend="egl")
    except Exception as exc:  # no Mesa EGL
        if os.environ.get("KGS_REQUIRE_BROWSER") == "1":
            raise
        pytest.skip(f"no EGL context: {exc}")


@pytest.fixture(scope="module")
def model(tiny_run):
    from kgs_app.viewer.model import ViewerModel
    from kgs_app.viewer.source import LocalSource

    m = ViewerModel(LocalSource(tiny_run))
    m.use_frame_camera(0)
    m.state.t = 0.5
    m.sync()
    return m


def draw(model, egl):
    from kgs_app.viewer.gl_renderer import render_offscreen

    model.sync()
    s = model.state
    return render_offscreen(
        model.static,
        model.dynamic,
        s.viewmat,
        s.K,
        model.width,
        model.height,
        ctx=egl,
        show=s.show_mask,
        overlay=s.overlay,
        stride=s.stride,
        arrows=s.arrows,
    ).astype(np.float64)


def test_gl_frame_matches_cpu_rasteriser(model, egl):
    from kgs_core.data.formats import load_scene
    from kgs_core.export.bake import render_baked

    img = draw(model, egl)
    view = model.source.view
    g, _ = view.baked(0.5)
    cam = load_scene(view.run.scene_path()).frames[0].camera
    ref = np.clip(render_baked(g, cam, view.run.model.config.sh_degree).image.numpy(), 0, 1) * 255
    err = np.abs(img - np.round(ref)).mean()
    print(f"GL vs CPU rasteriser: mean abs error {err:.2f} / 255")
    assert img.std() > 5 and err < MAX_MEAN_ERROR


class HeadlessImgui:
    """A real imgui context without a window: frames are fed mouse events."""

    def __init__(self):
        from imgui_bundle import imgui

        self.imgui = imgui
        self.ctx = imgui.create_context()
        io = imgui.get_io()
        io.set_ini_filename(None)  # no imgui.ini left in the working directory
        io.display_size = imgui.ImVec2(900, 700)
        io.delta_time = 1 / 60
        io.backend_flags |= imgui.BackendFlags_.renderer_has_textures.value

    def frame(self, model, mouse=None, down=None):
        from kgs_app.viewer.controls import draw_controls

        io = self.imgui.get_io()
        if mouse is not None:
            io.add_mouse_pos_event(*mouse)
        if down is not None:
            io.add_mouse_button_event(0, down)
        self.imgui.new_frame()
        changed = draw_controls(model)
        self.imgui.render()
        return changed

    def click(self, model, label, at=0.5):
        from kgs_app.viewer.controls import RECTS

        self.frame(model)
        x0, y0, x1, y1 = RECTS[label]
        pos = (x0 + at * (x1 - x0), (y0 + y1) / 2)
        self.frame(model, mouse=pos)
        self.frame(model, down=True)
        changed = self.frame(model, down=False)
        self.frame(model, mouse=(899, 699))
        return changed

    def close(self):
        self.imgui.destroy_context(self.ctx)


def test_imgui_controls_change_what_is_drawn(model, egl):
    ui = HeadlessImgui()
    try:
        before = draw(model, egl)
        ui.click(model, "dynamic", at=0.05)
        assert model.state.show_dynamic is False
        no_dyn = draw(model, egl)
        assert np.abs(before - no_dyn).mean() > 0.5
        ui.click(model, "dynamic", at=0.05)
        assert model.state.show_dynamic is True
        assert np.abs(draw(model, egl) - before).max() <= 1
        # the time slider: click near its right end
        ui.click(model, "time", at=0.98)
        assert model.state.t > 0.9
        late = draw(model, egl)
        assert np.abs(late - before).mean() > 0.5
        # play advances time
        ui.click(model, "play", at=0.5)
        assert model.state.playing
        t0 = model.state.t
        model.advance(0.05)
        assert model.state.t != t0
        model.state.playing = False
        # tau slider: far right makes everything static
        ui.click(model, "tau", at=0.99)
        model.sync()
        assert model.source.meta["decomposition"]["dynamic"] < 5
    finally:
        ui.close()
        model.state.t, model.state.playing = 0.5, False


def test_window_under_xvfb(tiny_run, tmp_path):
    if not shutil.which("xvfb-run"):
        if os.environ.get("KGS_REQUIRE_BROWSER") == "1":
            raise RuntimeError("xvfb-run missing (apt-get install xvfb)")
        pytest.skip("xvfb-run not installed")
    shot = tmp_path / "window.png"
    r = subprocess.run(
        [
            "xvfb-run",
            "-a",
            "-s",
            "-screen 0 800x600x24",
            sys.executable,
            "-m",
            "kgs_app.cli",
            "view",
            str(tiny_run),
            "--frames",
            "5",
            "--screenshot",
            str(shot),
            "--time",
            "0.5",
        ],
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(shot))
    assert img.shape[2] == 3 and img.std() > 5


def test_remote_source_matches_local(tiny_run, tmp_path, egl):
    from kgs_app.viewer.gl_renderer import render_offscreen
    from kgs_app.viewer.source import LocalSource, RemoteSource
    from kgs_backend.launch import ServerProcess

    run_copy = tmp_path / "data"
    shutil.copytree(tiny_run.parent.parent, run_copy)
    with ServerProcess([run_copy / "runs" / tiny_run.name], tmp_path / "ws") as srv:
        remote = RemoteSource(srv.base, srv.runs[0]["id"])
        local = LocalSource(run_copy / "runs" / tiny_run.name)
        f = local.frames[0]
        imgs = []
        for src in (local, remote):
            st, dy = src.static(None), src.dynamic(0.25, 0.0, None)
            imgs.append(
                render_offscreen(st, dy, np.array(f["viewmat"]), np.array(f["K"]), f["width"], f["height"], ctx=egl).astype(np.float64)
            )
        assert np.abs(imgs[0] - imgs[1]).max() <= 2
        assert remote.set_tau(1.0)["dynamic"] == 0
        remote.close()


def test_as_captured_shows_the_learned_camera_shake_as_the_cpu_rasteriser_does(copy_run, egl):
    """A run that kept its camera shake (`shake_run`): the static splats blurred in the shader
    (Σ + s sᵀ / 12 with s = A x + b, the mass-keeping opacity) match the CPU rasteriser's render
    of the server's bake at that exposure; the frame is visibly blurred against the sharp one."""
    from conftest import shake_run

    from kgs_app.viewer.model import ViewerModel
    from kgs_app.viewer.source import LocalSource
    from kgs_core.data.formats import load_scene
    from kgs_core.evaluate import gradient_energy
    from kgs_core.export.bake import render_baked

    shake_run(copy_run)
    m = ViewerModel(LocalSource(copy_run))
    m.use_frame_camera(0)
    m.state.t = 0.5
    sharp = draw(m, egl)
    m.state.exposure_captured = True
    assert m.shake() is not None
    m.sync()
    captured = render_offscreen_shaken(m, egl)
    view = m.source.view
    g, _ = view.baked(0.5, float(m.source.meta["exposure"]))
    cam = load_scene(view.run.scene_path()).frames[0].camera
    ref = np.clip(render_baked(g, cam, view.run.model.config.sh_degree).image.numpy(), 0, 1) * 255
    err = np.abs(captured - np.round(ref)).mean()
    moved = np.abs(captured - sharp).mean()
    print(f"as captured, GL vs CPU rasteriser: mean abs error {err:.2f} / 255; against the sharp frame {moved:.2f}")
    everywhere = np.ones(sharp.shape[:2], bool)
    assert err < MAX_MEAN_ERROR < moved
    assert gradient_energy(captured / 255, everywhere) < 0.8 * gradient_energy(sharp / 255, everywhere)


def render_offscreen_shaken(model, egl):
    from kgs_app.viewer.gl_renderer import render_offscreen

    s = model.state
    return render_offscreen(model.static, model.dynamic, s.viewmat, s.K, model.width, model.height, ctx=egl, shake=model.shake()).astype(
        np.float64
    )
