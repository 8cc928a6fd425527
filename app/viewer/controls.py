"""The imgui control panel, shared in spirit with the web viewer: time, sets, overlays, τ with
the K histogram, exposure, LoD, camera, screenshot."""

from __future__ import annotations

import math

import numpy as np
from imgui_bundle import imgui

from .model import ViewerModel

# Screen rectangle of each control after the last frame (label -> (x0, y0, x1, y1)): lets
# scripts and tests click a control by name.
RECTS: dict[str, tuple[float, float, float, float]] = {}


def _track(label: str, frame_only: bool = False) -> None:
    """`frame_only`: a slider's own frame, without its label (clicks there set the value)."""
    a, b = imgui.get_item_rect_min(), imgui.get_item_rect_max()
    x1 = a.x + imgui.calc_item_width() if frame_only else b.x
    RECTS[label] = (a.x, a.y, x1, b.y)


def draw_controls(model: ViewerModel) -> bool:
    """Draws the panel (inside the current imgui frame); returns True when the state changed."""
    s = model.state
    m = model.source.meta
    changed = False
    imgui.set_next_window_pos(imgui.ImVec2(0, 0), imgui.Cond_.first_use_ever)
    imgui.set_next_window_size(imgui.ImVec2(300, 520), imgui.Cond_.first_use_ever)
    imgui.begin("Kinematics-GS")
    imgui.text(f"{m['name']}: {m['decomposition']['gaussians']:,} Gaussians")
    c, t = imgui.slider_float("time", s.t, 0.0, 1.0, "%.3f")
    _track("time", frame_only=True)
    if c:
        s.t, changed = t, True
    clicked = imgui.button("Pause" if s.playing else "Play")
    _track("play")
    if clicked:
        s.playing, changed = not s.playing, True
    imgui.same_line()
    if imgui.button("<"):
        s.t, changed = max(0.0, s.t - m["dt"]), True
    imgui.same_line()
    if imgui.button(">"):
        s.t, changed = min(1.0, s.t + m["dt"]), True
    imgui.same_line()
    c, s.speed = imgui.slider_float("speed", s.speed, 0.25, 4.0, "%.2fx")
    imgui.separator()
    c1, s.show_static = imgui.checkbox("static", s.show_static)
    _track("static")
    imgui.same_line()
    c2, s.show_dynamic = imgui.checkbox("dynamic", s.show_dynamic)
    _track("dynamic")
    decomposition = m["decomposition"]
    imgui.text(f"static {decomposition['static_kept']:,}  dynamic {decomposition['dynamic_kept']:,}")
    c3, s.overlay = imgui.combo("overlay", s.overlay, ["colours", "static/dynamic tint", "velocity ellipses"])
    c4, s.arrows = imgui.checkbox("velocity arrows", s.arrows)
    _track("arrows")
    c5, s.stride = imgui.slider_int("density 1/", s.stride, 1, 32)
    changed |= c1 or c2 or c3 or c4 or c5
    imgui.separator()
    hist = np.asarray(m["histogram"]["counts"], dtype=np.float32)
    imgui.plot_histogram("log10 K", np.log1p(hist), graph_size=imgui.ImVec2(0, 50))
    c, lt = imgui.slider_float("log10 tau", math.log10(s.tau), -12.0, 0.0, "%.2f")
    _track("tau", frame_only=True)
    if c:
        s.tau, changed = 10.0**lt, True
    imgui.separator()
    c6, s.exposure_captured = imgui.checkbox("as captured (blur)", s.exposure_captured)
    _track("exposure")
    levels = [f"LoD {i}" for i in range(1, m["lod_levels"] + 1)]
    cur = (s.lod or m["lod_levels"]) - 1
    c7, sel = imgui.combo("level", cur, levels)
    if c7:
        s.lod = sel + 1
    c8, mode = imgui.combo("camera", ["orbit", "fly"].index(s.mode), ["orbit", "fly"])
    if c8:
        s.mode = ["orbit", "fly"][mode]
    if imgui.button("input camera"):
        f = model.nearest_frame()
        if f is not None:
            model.use_frame_camera(f["index"])
            changed = True
    imgui.same_line()
    if imgui.button("screenshot"):
        s.screenshot = "kgs-screenshot.png"
    changed |= c6 or c7 or c8
    imgui.end()
    return changed
