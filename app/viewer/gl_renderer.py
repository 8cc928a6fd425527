"""Splats with OpenGL 3.3 through moderngl, in whatever context is current (a window's, or a
headless EGL context): instanced quads over each splat's 2D footprint, drawn nearest first with
front-to-back blending. The same rules as the CPU rasteriser and the browser: alpha =
min(0.99, o exp(-1/2 d^T S^-1 d)), skipped below 1/255, 0.3 px^2 low-pass; SH DC colour only."""

from __future__ import annotations

import moderngl
import numpy as np

from kgs_frontend import ROOT as FRONTEND_ROOT

from .source import SplatSet

SHADERS = FRONTEND_ROOT / "shaders"  # shared with the browser

VERT_MAIN = """
uniform mat4 u_view;      // world-to-camera (OpenCV), column-major
uniform vec4 u_intr;      // fx, fy, cx, cy
uniform vec2 u_size;
uniform int u_show;
uniform int u_overlay;
uniform int u_stride;
uniform int u_shake;      // 1: blur the static splats along the camera's shake, sweep A x + b
uniform mat3 u_shake_A;   // over the exposure (the dynamic set arrives blurred)
uniform vec3 u_shake_b;
in vec2 a_corner;
in vec3 i_pos;
in vec3 i_cov_a;          // xx, xy, xz
in vec3 i_cov_b;          // yy, yz, zz
in vec4 i_rgba;
in float i_dynamic;
in float i_index;
out vec4 v_color;
out vec2 v_offset;
out vec3 v_conic;
flat out int v_solid;
void main() {
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  bool dyn = i_dynamic > 0.5;
  if (((u_show & 1) == 0 && !dyn) || ((u_show & 2) == 0 && dyn)) return;
  vec4 c = u_view * vec4(i_pos, 1.0);
  mat3 S = mat3(i_cov_a.x, i_cov_a.y, i_cov_a.z, i_cov_a.y, i_cov_b.x, i_cov_b.y, i_cov_a.z, i_cov_b.y, i_cov_b.z);
  float opacity = i_rgba.a;
  if (u_shake == 1 && !dyn) {
    vec3 sweep = u_shake_A * i_pos + u_shake_b;
    S += outerProduct(sweep, sweep) / 12.0;
    opacity *= sweep_opacity(c, S, mat3(u_view), u_intr, sweep);
  }
  bool solid = u_overlay == 2 && dyn && (int(i_index) % max(u_stride, 1)) == 0;
  vec2 center, major;
  float r;
  vec3 conic;
  if (!splat_footprint(c, S, mat3(u_view), u_intr, opacity, solid, center, r, conic, major)) return;
  vec2 off = a_corner * r;
  gl_Position = clip_position(center + off, u_size);
  v_offset = off;
  v_conic = conic;
  v_solid = solid ? 1 : 0;
  v_color = vec4(overlay_colour(i_rgba.rgb, dyn, solid, u_overlay, major), opacity);
}
"""


def shader_sources() -> tuple[str, str]:
    common = (SHADERS / "splat_common.glsl").read_text()
    frag = (SHADERS / "splat.frag.glsl").read_text()
    return "#version 330\n" + common + VERT_MAIN, "#version 330\n" + frag


LINE_VERT = """
#version 330
uniform mat4 u_view;
uniform vec4 u_intr;
uniform vec2 u_size;
in vec3 a_pos;
void main() {
  vec4 c = u_view * vec4(a_pos, 1.0);
  vec2 pix = vec2(u_intr.x * c.x / c.z + u_intr.z, u_intr.y * c.y / c.z + u_intr.w);
  gl_Position = c.z > 0.01 ? vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0) : vec4(0, 0, 2, 1);
}
"""

LINE_FRAG = """
#version 330
out vec4 frag;
void main() { frag = vec4(1.0, 0.85, 0.2, 1.0); }
"""

INSTANCE = np.dtype([("pos", "f4", 3), ("cov_a", "f4", 3), ("cov_b", "f4", 3), ("rgba", "f4", 4), ("dynamic", "f4"), ("index", "f4")])


def instances(static: SplatSet | None, dynamic: SplatSet | None) -> np.ndarray:
    parts = []
    for s, dyn in ((static, 0.0), (dynamic, 1.0)):
        if s is None or len(s) == 0:
            continue
        a = np.empty(len(s), dtype=INSTANCE)
        a["pos"] = s.positions
        a["cov_a"] = s.covars[:, 0:3]
        a["cov_b"] = s.covars[:, 3:6]
        a["rgba"] = s.rgba / 255.0
        a["dynamic"] = dyn
        a["index"] = s.index
        parts.append(a)
    return np.concatenate(parts) if parts else np.zeros(0, dtype=INSTANCE)


class GLSplatRenderer:
    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        vert, frag = shader_sources()
        self.prog = ctx.program(vertex_shader=vert, fragment_shader=frag)
        self.line_prog = ctx.program(vertex_shader=LINE_VERT, fragment_shader=LINE_FRAG)
        self.quad = ctx.buffer(np.array([-1, -1, 1, -1, 1, 1, -1, 1], dtype="f4").tobytes())
        self.inst = np.zeros(0, dtype=INSTANCE)
        self.inst_buf = None
        self.vao = None
        self.lines = None
        self._order_key = None

    def set_splats(self, static: SplatSet | None, dynamic: SplatSet | None) -> None:
        self.inst = instances(static, dynamic)
        self._order_key = None
        self.arrows_from(dynamic)

    def arrows_from(self, dynamic: SplatSet | None, stride: int = 4, length: float = 0.05) -> None:
        if dynamic is None or dynamic.velocity is None or len(dynamic) == 0:
            self.lines = None
            return
        p = dynamic.positions[::stride]
        q = p + length * dynamic.velocity[::stride]
        seg = np.stack([p, q], 1).reshape(-1, 3).astype("f4")
        buf = self.ctx.buffer(seg.tobytes())
        self.lines = (self.ctx.vertex_array(self.line_prog, [(buf, "3f", "a_pos")]), len(seg))

    def _sort(self, viewmat: np.ndarray) -> None:
        """Front to back by camera depth; redone when the camera or the splats change."""
        key = tuple(np.round(viewmat[2], 6))
        if key == self._order_key:
            return
        self._order_key = key
        depth = self.inst["pos"] @ viewmat[2, :3] + viewmat[2, 3]
        order = np.argsort(depth, kind="stable")
        data = self.inst[order[depth[order] > 0.01]]
        self.count = len(data)
        if self.count == 0:
            self.vao = None
            return
        if self.inst_buf is None or self.inst_buf.size < data.nbytes:
            self.inst_buf = self.ctx.buffer(reserve=max(data.nbytes, 1024))
            self.vao = None
        self.inst_buf.write(data.tobytes())
        if self.vao is None:
            self.vao = self.ctx.vertex_array(
                self.prog,
                [
                    (self.quad, "2f", "a_corner"),
                    (self.inst_buf, "3f 3f 3f 4f 1f 1f/i", "i_pos", "i_cov_a", "i_cov_b", "i_rgba", "i_dynamic", "i_index"),
                ],
            )

    def draw(
        self,
        viewmat: np.ndarray,
        K: np.ndarray,
        width: int,
        height: int,
        show: int = 3,
        overlay: int = 0,
        stride: int = 4,
        arrows: bool = False,
        shake: np.ndarray | None = None,
    ) -> None:
        """`shake`: None, or the static splats' sweep over the exposure under the camera's shake,
        `(4, 3)` rows A then b, a still point x sweeping `A x + b` (`ViewerModel.shake`)."""
        ctx = self.ctx
        ctx.viewport = (0, 0, width, height)
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.enable(moderngl.BLEND)
        ctx.blend_func = (moderngl.ONE_MINUS_DST_ALPHA, moderngl.ONE, moderngl.ONE_MINUS_DST_ALPHA, moderngl.ONE)
        self._sort(viewmat)
        view = viewmat.astype("f4").T.tobytes()  # GLSL is column-major
        intr = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
        if self.vao is not None:
            p = self.prog
            p["u_view"].write(view)
            p["u_intr"].value = intr
            p["u_size"].value = (float(width), float(height))
            p["u_show"].value = show
            p["u_overlay"].value = overlay
            p["u_stride"].value = stride
            p["u_shake"].value = int(shake is not None)
            if shake is not None:
                p["u_shake_A"].write(np.ascontiguousarray(shake[:3].T, dtype="f4").tobytes())  # column-major
                p["u_shake_b"].value = tuple(float(v) for v in shake[3])
            self.vao.render(moderngl.TRIANGLE_FAN, vertices=4, instances=self.count)
        if arrows and self.lines is not None:
            ctx.disable(moderngl.BLEND)
            lp = self.line_prog
            lp["u_view"].write(view)
            lp["u_intr"].value = intr
            lp["u_size"].value = (float(width), float(height))
            self.lines[0].render(moderngl.LINES, vertices=self.lines[1])


def render_offscreen(
    static: SplatSet | None, dynamic: SplatSet | None, viewmat, K, width: int, height: int, ctx: moderngl.Context | None = None, **kw
) -> np.ndarray:
    """`(H, W, 3)` uint8 from a headless context (EGL on Mesa when none is given)."""
    ctx = ctx or moderngl.create_standalone_context(backend="egl")
    fbo = ctx.framebuffer(color_attachments=[ctx.texture((width, height), 4)])
    fbo.use()
    fbo.clear(0.0, 0.0, 0.0, 0.0)
    r = GLSplatRenderer(ctx)
    r.set_splats(static, dynamic)
    r.draw(np.asarray(viewmat, dtype=np.float64), np.asarray(K, dtype=np.float64), width, height, **kw)
    data = np.frombuffer(fbo.read(components=3), dtype=np.uint8).reshape(height, width, 3)
    return data[::-1].copy()  # GL rows go bottom-up
