// Reading splat files a user drops on the page: antimatter15 `.splat` (32-byte records) and
// 3DGS `.ply` (binary little-endian: x y z, f_dc_*, f_rest_*, opacity, scale_*, rot_*), into
// the set the renderer draws (as a parsed server buffer: positions, covariances, rgba, index),
// with a `.ply`'s view-dependent colour as float16 coefficients by index. No DOM: node-tested.

const C0 = 0.28209479177387814;

// float32 -> float16 bits, rounded to nearest (the SH texture holds halves).
export function floatToHalf(v) {
  const f = new Float32Array([v]), u = new Uint32Array(f.buffer)[0];
  const sign = (u >> 16) & 0x8000, exp = ((u >> 23) & 0xff) - 112, mant = u & 0x7fffff;
  if (exp >= 31) return sign | 0x7bff;  // past the largest half: clipped to it
  if (exp <= 0) return exp < -10 ? sign : sign | Math.round((mant | 0x800000) / 2 ** (14 - exp));
  const h = (exp << 10) + Math.round(mant / 8192);  // a carry out of the mantissa bumps the exponent
  return sign | Math.min(h, 0x7bff);
}

// Sigma = R diag(s^2) R^T as (xx, xy, xz, yy, yz, zz), from scales and a quaternion (w, x, y, z).
export function covarianceOf(s, q) {
  const n = Math.hypot(q[0], q[1], q[2], q[3]) || 1;
  const [w, x, y, z] = q.map((v) => v / n);
  const R = [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
             2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
             2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)];
  const m = (i, j) => R[3 * i] * R[3 * j] * s[0] * s[0] + R[3 * i + 1] * R[3 * j + 1] * s[1] * s[1]
    + R[3 * i + 2] * R[3 * j + 2] * s[2] * s[2];
  return [m(0, 0), m(0, 1), m(0, 2), m(1, 1), m(1, 2), m(2, 2)];
}

function emptySet(n) {
  return { header: { kind: "static", count: n }, count: n, positions: new Float32Array(3 * n),
           covariances: new Float32Array(6 * n), rgba: new Uint8Array(4 * n), index: Uint32Array.from({ length: n }, (_, i) => i),
           velocity: null };
}

export function parseSplatFile(buffer) {
  if (buffer.byteLength % 32 || !buffer.byteLength) throw new Error(`not a .splat file: ${buffer.byteLength} bytes is not a whole number of 32-byte splats`);
  const n = buffer.byteLength / 32, dv = new DataView(buffer), u8 = new Uint8Array(buffer);
  const set = emptySet(n);
  for (let i = 0; i < n; i++) {
    const o = 32 * i;
    for (let k = 0; k < 3; k++) set.positions[3 * i + k] = dv.getFloat32(o + 4 * k, true);
    const s = [0, 1, 2].map((k) => dv.getFloat32(o + 12 + 4 * k, true));
    const q = [0, 1, 2, 3].map((k) => (u8[o + 28 + k] - 128) / 128);
    set.covariances.set(covarianceOf(s, q), 6 * i);
    set.rgba.set(u8.subarray(o + 24, o + 28), 4 * i);
  }
  return set;
}

const PLY_TYPES = { float: ["getFloat32", 4], float32: ["getFloat32", 4], double: ["getFloat64", 8], float64: ["getFloat64", 8],
  uchar: ["getUint8", 1], uint8: ["getUint8", 1], char: ["getInt8", 1], int8: ["getInt8", 1], short: ["getInt16", 2],
  int16: ["getInt16", 2], ushort: ["getUint16", 2], uint16: ["getUint16", 2], int: ["getInt32", 4], int32: ["getInt32", 4],
  uint: ["getUint32", 4], uint32: ["getUint32", 4] };

export function parsePlyFile(buffer) {
  const bytes = new Uint8Array(buffer);
  const head = new TextDecoder().decode(bytes.subarray(0, Math.min(bytes.length, 64 * 1024)));
  const end = head.indexOf("end_header\n");
  if (!head.startsWith("ply\n") || end < 0) throw new Error("not a .ply file (no ply header)");
  const lines = head.slice(0, end).split("\n");
  if (!lines.includes("format binary_little_endian 1.0")) throw new Error(".ply: only binary little-endian files are read");
  let n = -1, inVertex = false, stride = 0;
  const props = {};
  for (const line of lines) {
    const w = line.trim().split(/\s+/);
    if (w[0] === "element") { inVertex = w[1] === "vertex"; if (inVertex) n = parseInt(w[2], 10); else if (n >= 0 && stride) break; }
    if (w[0] === "property" && inVertex) {
      if (w[1] === "list") throw new Error(".ply: list properties in the vertex element are not splats");
      const t = PLY_TYPES[w[1]];
      if (!t) throw new Error(`.ply: unknown property type ${w[1]}`);
      props[w[2]] = [stride, t[0]];
      stride += t[1];
    }
  }
  for (const name of ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]) {
    if (!(name in props)) throw new Error(`.ply: no ${name} property: not a 3DGS splat file`);
  }
  const base = end + "end_header\n".length;  // the header is ASCII: characters are bytes
  if (n < 1 || base + n * stride > bytes.length) throw new Error(`.ply: ${n} vertices of ${stride} bytes do not fit the file`);
  const dv = new DataView(buffer);
  const get = (i, name) => { const [off, fn] = props[name]; return dv[fn](base + i * stride + off, true); };
  const rest = Object.keys(props).filter((k) => k.startsWith("f_rest_")).length;
  const bases = [0, 3, 8, 15].includes(rest / 3) ? rest / 3 : 0;  // coefficients after the DC term, per channel
  const set = emptySet(n);
  const halfs = bases ? new Uint16Array(n * bases * 3) : null;
  for (let i = 0; i < n; i++) {
    for (let k = 0; k < 3; k++) set.positions[3 * i + k] = get(i, "xyz"[k]);
    const s = [0, 1, 2].map((k) => Math.exp(get(i, `scale_${k}`)));
    set.covariances.set(covarianceOf(s, [0, 1, 2, 3].map((k) => get(i, `rot_${k}`))), 6 * i);
    for (let c = 0; c < 3; c++) {
      const v = "f_dc_0" in props ? 0.5 + C0 * get(i, `f_dc_${c}`) : get(i, ["red", "green", "blue"][c]) / 255;
      set.rgba[4 * i + c] = Math.round(255 * Math.min(1, Math.max(0, v)));
    }
    set.rgba[4 * i + 3] = Math.round(255 / (1 + Math.exp(-get(i, "opacity"))));
    // f_rest is channel-major (every R coefficient, then G, then B); the texture wants RGB per coefficient.
    for (let b = 0; b < bases; b++) for (let c = 0; c < 3; c++) {
      halfs[(i * bases + b) * 3 + c] = floatToHalf(get(i, `f_rest_${c * bases + b}`));
    }
  }
  set.sh = bases ? { header: { kind: "sh" }, count: n, bases, halfs } : null;
  return set;
}

// A dropped file by its name: .splat or .ply.
export function parseSplatOrPly(name, buffer) {
  if (/\.splat$/i.test(name)) return parseSplatFile(buffer);
  if (/\.ply$/i.test(name)) return parsePlyFile(buffer);
  throw new Error(`${name}: drop a .ply or .splat file`);
}
