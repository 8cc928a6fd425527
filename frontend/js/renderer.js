// WebGL2 splat renderer. Splats live in one RGBA32UI texture (layout in pack.js); each is drawn
// as an instanced quad covering its 2D footprint, front to back (order from the sort worker),
// blended under what is already drawn: C += (1 - A) * alpha * c, A += (1 - A) * alpha. The
// per-pixel alpha follows the CPU rasteriser: alpha = min(0.99, o * exp(-0.5 d^T S^-1 d)),
// skipped below 1/255, with the same 0.3 px^2 low-pass added to the 2D covariance.

import { TEX_WIDTH, SPLATS_PER_ROW } from "./pack.js";

// The view-dependent colour texture (RGBA32UI): each Gaussian's SH coefficients after the DC
// term as float16 pairs, SH_TEXELS texels each, SH_PER_ROW Gaussians a row, by Gaussian index.
export const SH_PER_ROW = 512;
export function shTexels(bases) { return Math.ceil((3 * bases) / 8); }

// Packs `halfs` (count x bases x 3 float16 bits) into the texture's words.
export function packSH(halfs, count, bases) {
  const texels = shTexels(bases), rows = Math.max(1, Math.ceil(count / SH_PER_ROW));
  const words = new Uint32Array(rows * SH_PER_ROW * texels * 4);
  const per = 3 * bases;
  for (let i = 0; i < count; i++) {
    const w = i * texels * 4;
    for (let j = 0; j < per; j++) words[w + (j >> 1)] |= halfs[i * per + j] << (16 * (j & 1));
  }
  return { words, rows, texels };
}
// Inputs of the WebGL2 vertex shader; the footprint math and the overlay colours come from
// shaders/splat_common.glsl (shared with the desktop viewer), the fragment shader from
// shaders/splat.frag.glsl.
const VERT_MAIN = `
uniform usampler2D u_splats;
uniform mat4 u_view;        // world-to-camera (OpenCV), column-major for GLSL
uniform vec4 u_intr;        // fx, fy, cx, cy in pixels
uniform vec2 u_size;        // viewport in pixels
uniform int u_show;         // bit 0 static, bit 1 dynamic
uniform int u_overlay;      // 0 none, 1 static/dynamic tint, 2 velocity ellipses
uniform int u_stride;       // overlay density: every k-th dynamic splat in ellipse mode
uniform usampler2D u_sh;    // view-dependent colour (see packSH)
uniform int u_sh_bases;     // SH coefficients after the DC term: 0 (DC only), 3, 8 or 15
uniform int u_sh_texels;
uniform vec3 u_eye;         // the camera centre in world coordinates
uniform int u_shake;        // 1: blur the static splats along the camera's shake, sweep A x + b
uniform mat3 u_shake_A;     // over the exposure (dynamic splats arrive blurred by the server)
uniform vec3 u_shake_b;
in vec2 a_corner;
in uint a_index;
out vec4 v_color;
out vec2 v_offset;          // pixels from the centre
out vec3 v_conic;
flat out int v_solid;

// Coefficient j (of 3 x bases, colour-minor) of Gaussian id, a float16 unpacked.
float sh_coef(int id, int j) {
  ivec2 texel = ivec2((id % ${SH_PER_ROW}) * u_sh_texels + (j >> 3), id / ${SH_PER_ROW});
  uvec4 t = texelFetch(u_sh, texel, 0);
  int w = (j >> 1) & 3;
  uint word = w == 0 ? t.x : w == 1 ? t.y : w == 2 ? t.z : t.w;
  vec2 pair = unpackHalf2x16(word);
  return (j & 1) == 0 ? pair.x : pair.y;
}

// The colour the SH terms after the DC add, seen along d (kgs_core/render/sh.py's basis).
vec3 sh_view_colour(int id, vec3 d) {
  float x = d.x, y = d.y, z = d.z, xx = x * x, yy = y * y, zz = z * z;
  float b[15] = float[15](-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x,
    1.0925484305920792 * x * y, -1.0925484305920792 * y * z, 0.31539156525252005 * (2.0 * zz - xx - yy),
    -1.0925484305920792 * x * z, 0.5462742152960396 * (xx - yy),
    -0.5900435899266435 * y * (3.0 * xx - yy), 2.890611442640554 * x * y * z,
    -0.4570457994644658 * y * (4.0 * zz - xx - yy), 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
    -0.4570457994644658 * x * (4.0 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
    -0.5900435899266435 * x * (xx - 3.0 * yy));
  vec3 c = vec3(0.0);
  for (int k = 0; k < 15; k++) {
    if (k >= u_sh_bases) break;
    c += b[k] * vec3(sh_coef(id, 3 * k), sh_coef(id, 3 * k + 1), sh_coef(id, 3 * k + 2));
  }
  return c;
}

void main() {
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);
  int i = int(a_index);
  ivec2 base = ivec2((i % ${SPLATS_PER_ROW}) * 3, i / ${SPLATS_PER_ROW});
  uvec4 t0 = texelFetch(u_splats, base, 0);
  uvec4 t1 = texelFetch(u_splats, base + ivec2(1, 0), 0);
  uvec4 t2 = texelFetch(u_splats, base + ivec2(2, 0), 0);
  uint flags = t2.z;
  bool dyn = (flags & 1u) != 0u;
  if (((u_show & 1) == 0 && !dyn) || ((u_show & 2) == 0 && dyn)) return;
  vec4 c = u_view * vec4(uintBitsToFloat(t0.xyz), 1.0);
  float xx = uintBitsToFloat(t1.x), xy = uintBitsToFloat(t1.y), xz = uintBitsToFloat(t1.z);
  float yy = uintBitsToFloat(t1.w), yz = uintBitsToFloat(t2.x), zz = uintBitsToFloat(t2.y);
  mat3 S = mat3(xx, xy, xz, xy, yy, yz, xz, yz, zz);
  vec4 rgba = vec4(float(t0.w & 255u), float((t0.w >> 8) & 255u), float((t0.w >> 16) & 255u), float(t0.w >> 24)) / 255.0;
  if (u_shake == 1 && !dyn) {
    vec3 sweep = u_shake_A * uintBitsToFloat(t0.xyz) + u_shake_b;
    S += outerProduct(sweep, sweep) / 12.0;
    rgba.a *= sweep_opacity(c, S, mat3(u_view), u_intr, sweep);
  }
  if (u_sh_bases > 0) {
    vec3 world = uintBitsToFloat(t0.xyz);
    rgba.rgb = clamp(rgba.rgb + sh_view_colour(int(t2.w), normalize(world - u_eye)), 0.0, 1.0);
  }
  bool solid = u_overlay == 2 && dyn && (int(t2.w) % max(u_stride, 1)) == 0;
  vec2 center, major;
  float r;
  vec3 conic;
  if (!splat_footprint(c, S, mat3(u_view), u_intr, rgba.a, solid, center, r, conic, major)) return;
  vec2 off = a_corner * r;
  gl_Position = clip_position(center + off, u_size);
  v_offset = off;
  v_conic = conic;
  v_solid = solid ? 1 : 0;
  vec3 col = overlay_colour(rgba.rgb, dyn, solid, u_overlay, major);
  if ((flags & 2u) != 0u) col = mix(col, vec3(1.0, 0.1, 0.6), 0.7);  // selected
  v_color = vec4(col, rgba.a);
}`;

const ES_HEADER = `#version 300 es
precision highp float;
precision highp int;
precision highp usampler2D;
`;

async function shaderSources() {
  const [common, frag] = await Promise.all(["splat_common.glsl", "splat.frag.glsl"].map(async (name) => {
    const r = await fetch(new URL(`../shaders/${name}`, import.meta.url));
    if (!r.ok) throw new Error(`shader ${name}: ${r.status}`);
    return r.text();
  }));
  return { vert: ES_HEADER + common + VERT_MAIN, frag: ES_HEADER + frag };
}

const LINE_VERT = `#version 300 es
precision highp float;
uniform mat4 u_view;
uniform vec4 u_intr;
uniform vec2 u_size;
in vec3 a_pos;
in float a_head;
out float v_head;
void main() {
  vec4 c = u_view * vec4(a_pos, 1.0);
  vec2 pix = vec2(u_intr.x * c.x / c.z + u_intr.z, u_intr.y * c.y / c.z + u_intr.w);
  gl_Position = c.z > 0.01 ? vec4(2.0 * pix.x / u_size.x - 1.0, 1.0 - 2.0 * pix.y / u_size.y, 0.0, 1.0) : vec4(0, 0, 2, 1);
  v_head = a_head;
}`;

// The background, drawn last under the splats (the same front-to-back blending): a full-screen
// triangle of one colour.
const BG_VERT = `#version 300 es
void main() { gl_Position = vec4(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0, 0.0, 1.0); }`;
const BG_FRAG = `#version 300 es
precision highp float;
uniform vec3 u_bg;
out vec4 frag;
void main() { frag = vec4(u_bg, 1.0); }`;

const LINE_FRAG = `#version 300 es
precision highp float;
in float v_head;
out vec4 frag;
void main() { frag = vec4(mix(vec3(1.0, 0.9, 0.2), vec3(1.0, 0.2, 0.1), v_head), 1.0); }`;

function compile(gl, vs, fs) {
  const prog = gl.createProgram();
  for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const sh = gl.createShader(type);
    gl.shaderSource(sh, src);
    gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(sh));
    gl.attachShader(prog, sh);
  }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(prog));
  return prog;
}

// Row-major 4x4 (ours) -> column-major Float32Array (GLSL).
function toGL(m) {
  const o = new Float32Array(16);
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) o[4 * c + r] = m[4 * r + c];
  return o;
}

export class SplatRenderer {
  static async create(canvas) {
    return new SplatRenderer(canvas, await shaderSources());
  }

  constructor(canvas, sources) {
    const gl = canvas.getContext("webgl2", { antialias: false, premultipliedAlpha: true, preserveDrawingBuffer: true });
    if (!gl) throw new Error("WebGL2 is not available in this browser");
    this.gl = gl;
    this.canvas = canvas;
    this.prog = compile(gl, sources.vert, sources.frag);
    this.lineProg = compile(gl, LINE_VERT, LINE_FRAG);
    this.bgProg = compile(gl, BG_VERT, BG_FRAG);
    this.bgColour = gl.getUniformLocation(this.bgProg, "u_bg");
    this.tex = gl.createTexture();
    this.shTex = gl.createTexture();
    this.shBases = 0;
    this.count = 0;
    this.order = new Uint32Array(0);
    this.vao = gl.createVertexArray();
    gl.bindVertexArray(this.vao);
    const quad = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, quad);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 1, -1, 1, 1, -1, 1]), gl.STATIC_DRAW);
    const aCorner = gl.getAttribLocation(this.prog, "a_corner");
    gl.enableVertexAttribArray(aCorner);
    gl.vertexAttribPointer(aCorner, 2, gl.FLOAT, false, 0, 0);
    this.indexBuf = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuf);
    const aIndex = gl.getAttribLocation(this.prog, "a_index");
    gl.enableVertexAttribArray(aIndex);
    gl.vertexAttribIPointer(aIndex, 1, gl.UNSIGNED_INT, 0, 0);
    gl.vertexAttribDivisor(aIndex, 1);
    gl.bindVertexArray(null);
    this.lineVao = gl.createVertexArray();
    this.lineBuf = gl.createBuffer();
    gl.bindVertexArray(this.lineVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
    const aPos = gl.getAttribLocation(this.lineProg, "a_pos");
    const aHead = gl.getAttribLocation(this.lineProg, "a_head");
    gl.enableVertexAttribArray(aPos);
    gl.vertexAttribPointer(aPos, 3, gl.FLOAT, false, 16, 0);
    gl.enableVertexAttribArray(aHead);
    gl.vertexAttribPointer(aHead, 1, gl.FLOAT, false, 16, 12);
    gl.bindVertexArray(null);
    this.lineCount = 0;
    this.uniforms = {};
    for (const name of ["u_splats", "u_view", "u_intr", "u_size", "u_show", "u_overlay", "u_stride", "u_sh", "u_sh_bases",
                        "u_sh_texels", "u_eye", "u_shake", "u_shake_A", "u_shake_b"]) {
      this.uniforms[name] = gl.getUniformLocation(this.prog, name);
    }
    this.lineUniforms = {};
    for (const name of ["u_view", "u_intr", "u_size"]) this.lineUniforms[name] = gl.getUniformLocation(this.lineProg, name);
  }

  // words: Uint32Array of rows x TEX_WIDTH x 4; rows: texture height.
  upload(words, rows, count, fromRow = 0) {
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, this.tex);
    if (fromRow === 0 || rows !== this.rows) {
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32UI, TEX_WIDTH, rows, 0, gl.RGBA_INTEGER, gl.UNSIGNED_INT, words);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
      this.rows = rows;
    } else {
      const sub = words.subarray(fromRow * TEX_WIDTH * 4);
      gl.texSubImage2D(gl.TEXTURE_2D, 0, 0, fromRow, TEX_WIDTH, rows - fromRow, gl.RGBA_INTEGER, gl.UNSIGNED_INT, sub);
    }
    this.count = count;
  }

  // The level's view-dependent colour (a parsed "sh" buffer), by Gaussian index.
  uploadSH(set) {
    const gl = this.gl;
    const { words, rows, texels } = packSH(set.halfs, set.count, set.bases);
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.shTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32UI, SH_PER_ROW * texels, rows, 0, gl.RGBA_INTEGER, gl.UNSIGNED_INT, words);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.activeTexture(gl.TEXTURE0);
    this.shBases = set.bases;
    this.shTexels = texels;
  }

  setOrder(order) {
    const gl = this.gl;
    this.order = order;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.indexBuf);
    gl.bufferData(gl.ARRAY_BUFFER, order, gl.DYNAMIC_DRAW);
  }

  // lines: Float32Array of (x, y, z, head) per vertex, two vertices a segment
  setLines(lines) {
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.lineBuf);
    gl.bufferData(gl.ARRAY_BUFFER, lines, gl.DYNAMIC_DRAW);
    this.lineCount = lines.length / 4;
  }

  // `sh`: add the view-dependent colour (when uploaded); `background`: RGB in [0, 1]; `shake`:
  // null, or the camera's sweep over the exposure for the static splats, {A: 9 numbers row-major,
  // b: 3}, a still point x sweeping A x + b (shakeSweep).
  draw({ viewmat, K, show = 3, overlay = 0, stride = 1, arrows = false, sh = true, background = [0, 0, 0], shake = null }) {
    const gl = this.gl;
    const w = this.canvas.width, h = this.canvas.height;
    gl.viewport(0, 0, w, h);
    gl.clearColor(0, 0, 0, 0);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.disable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFuncSeparate(gl.ONE_MINUS_DST_ALPHA, gl.ONE, gl.ONE_MINUS_DST_ALPHA, gl.ONE);
    const view = toGL(viewmat);
    const intr = new Float32Array([K[0], K[4], K[2], K[5]]);
    if (this.order.length && this.rows) {
      gl.useProgram(this.prog);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, this.tex);
      const u = this.uniforms;
      gl.uniform1i(u.u_splats, 0);
      gl.uniformMatrix4fv(u.u_view, false, view);
      gl.uniform4fv(u.u_intr, intr);
      gl.uniform2f(u.u_size, w, h);
      gl.uniform1i(u.u_show, show);
      gl.uniform1i(u.u_overlay, overlay);
      gl.uniform1i(u.u_stride, stride);
      gl.uniform1i(u.u_shake, shake ? 1 : 0);
      if (shake) {
        gl.uniformMatrix3fv(u.u_shake_A, true, new Float32Array(shake.A));  // (row-major, transposed in)
        gl.uniform3fv(u.u_shake_b, new Float32Array(shake.b));
      }
      const bases = sh ? this.shBases : 0;
      gl.uniform1i(u.u_sh_bases, bases);
      if (bases) {
        gl.activeTexture(gl.TEXTURE1);
        gl.bindTexture(gl.TEXTURE_2D, this.shTex);
        gl.uniform1i(u.u_sh, 1);
        gl.uniform1i(u.u_sh_texels, this.shTexels);
        const m = viewmat;  // the centre -R^T t of the row-major world-to-camera
        gl.uniform3f(u.u_eye, -(m[0] * m[3] + m[4] * m[7] + m[8] * m[11]), -(m[1] * m[3] + m[5] * m[7] + m[9] * m[11]),
                     -(m[2] * m[3] + m[6] * m[7] + m[10] * m[11]));
        gl.activeTexture(gl.TEXTURE0);
      }
      gl.bindVertexArray(this.vao);
      gl.drawArraysInstanced(gl.TRIANGLE_FAN, 0, 4, this.order.length);
      gl.bindVertexArray(null);
    }
    {  // under everything drawn, C += (1 - A) * background: the picture ends opaque
      gl.useProgram(this.bgProg);
      gl.uniform3f(this.bgColour, background[0], background[1], background[2]);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }
    if (arrows && this.lineCount) {
      gl.disable(gl.BLEND);
      gl.useProgram(this.lineProg);
      const u = this.lineUniforms;
      gl.uniformMatrix4fv(u.u_view, false, view);
      gl.uniform4fv(u.u_intr, intr);
      gl.uniform2f(u.u_size, w, h);
      gl.bindVertexArray(this.lineVao);
      gl.drawArrays(gl.LINES, 0, this.lineCount);
      gl.bindVertexArray(null);
    }
  }
}

// The static splats' sweep over an exposure of `exposure` frame intervals `dt` (normalised time)
// under the camera's shake {w, b} (a still point x moves like w × x + b per unit of time,
// kgs_core/train/camera_motion.py): {A, b} for draw's `shake`.
export function shakeSweep(shake, dt, exposure) {
  const k = dt * exposure, [wx, wy, wz] = shake.w;
  return { A: [0, -wz * k, wy * k, wz * k, 0, -wx * k, -wy * k, wx * k, 0], b: shake.b.map((v) => v * k) };
}

// The record of `records` (time-ordered {t, ...}) nearest in time to `t`, null without any.
export function nearestInTime(records, t) {
  let best = null;
  for (const r of records || []) if (best === null || Math.abs(r.t - t) < Math.abs(best.t - t)) best = r;
  return best;
}
