"""The native window: hello_imgui (GLFW + OpenGL 3) for the panel, moderngl drawing the splats
into the same context as the window's background."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .controls import draw_controls
from .gl_renderer import GLSplatRenderer
from .model import ViewerModel


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    import io

    from PIL import Image

    from kgs_core.io import atomic_write_bytes

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="PNG")
    return atomic_write_bytes(path, buf.getvalue())


def run_window(
    model: ViewerModel, width: int = 1280, height: int = 800, max_frames: int | None = None, screenshot: str | None = None
) -> None:
    import moderngl
    from imgui_bundle import hello_imgui, imgui

    gl = {"ctx": None, "renderer": None, "frames": 0, "last": time.perf_counter()}

    def background() -> None:
        if gl["ctx"] is None:
            gl["ctx"] = moderngl.create_context()
            gl["renderer"] = GLSplatRenderer(gl["ctx"])
        ctx, r = gl["ctx"], gl["renderer"]
        io = imgui.get_io()
        w = int(io.display_size.x * io.display_framebuffer_scale.x)
        h = int(io.display_size.y * io.display_framebuffer_scale.y)
        if (w, h) != (model.width, model.height) and w >= 16 and h >= 16:
            if model.state.mode == "orbit":
                model.width, model.height = w, h
                model.update_camera()
            else:  # keep the camera's field of view across the resize
                K = model.state.K.copy()
                K[0] *= w / model.width
                K[1] *= h / model.height
                model.state.K, model.width, model.height = K, w, h
        now = time.perf_counter()
        model.advance(now - gl["last"])
        gl["last"] = now
        if model.sync():
            r.set_splats(model.static, model.dynamic)
        ctx.screen.use()
        ctx.clear(0.0, 0.0, 0.0, 0.0)
        s = model.state
        r.draw(s.viewmat, s.K, w, h, show=s.show_mask, overlay=s.overlay, stride=s.stride, arrows=s.arrows, shake=model.shake())
        shot = s.screenshot or (screenshot if max_frames and gl["frames"] + 1 == max_frames else None)
        if shot:
            rgb = np.frombuffer(ctx.screen.read(viewport=(0, 0, w, h), components=3), dtype=np.uint8)
            save_png(shot, rgb.reshape(h, w, 3)[::-1].copy())
            print(f"screenshot: {shot}")
            s.screenshot = None

    def gui() -> None:
        draw_controls(model)
        io = imgui.get_io()
        if not io.want_capture_mouse:
            if imgui.is_mouse_dragging(imgui.MouseButton_.left):
                d = io.mouse_delta
                if model.state.mode == "orbit":
                    model.orbit(-4 * d.x / max(model.width, 1), 4 * d.y / max(model.height, 1))
            if io.mouse_wheel:
                if model.state.mode == "orbit":
                    model.zoom(float(np.exp(-0.1 * io.mouse_wheel)))
                else:
                    model.fly(0.05 * io.mouse_wheel, 0, 0)
        if model.state.mode == "fly" and not io.want_capture_keyboard:
            k = lambda key: imgui.is_key_down(key)  # noqa: E731
            f = 0.02 * (k(imgui.Key.w) - k(imgui.Key.s))
            rgt = 0.02 * (k(imgui.Key.d) - k(imgui.Key.a))
            up = 0.02 * (k(imgui.Key.e) - k(imgui.Key.q))
            if f or rgt or up:
                model.fly(f, rgt, up)
        gl["frames"] += 1
        if max_frames and gl["frames"] >= max_frames + 1:
            hello_imgui.get_runner_params().app_shall_exit = True

    params = hello_imgui.RunnerParams()
    params.app_window_params.window_title = f"Kinematics-GS: {model.source.meta['name']}"
    params.app_window_params.window_geometry.size = (width, height)
    params.callbacks.show_gui = gui
    params.callbacks.custom_background = background
    params.fps_idling.enable_idling = False
    params.ini_disable = True
    hello_imgui.run(params)
