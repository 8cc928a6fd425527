// Parsing the server's splat buffers (layout documented in backend/splats.py):
// "KGS1", uint32 header length H, H bytes of JSON, count x 32-byte records
// (position 3 x f32, covariance 6 x f16 in units of cov_scale, RGBA 4 x u8, index u32),
// then, if header.velocity, count x 3 x f16 velocities. A "sh" buffer (header.kind) holds
// count x bases x 3 f16 view-dependent colour coefficients instead, by Gaussian index.

export const RECORD_BYTES = 32;

export function halfToFloat(h) {
  const s = (h & 0x8000) ? -1 : 1;
  const e = (h >> 10) & 0x1f;
  const f = h & 0x3ff;
  if (e === 0) return s * Math.pow(2, -14) * (f / 1024);
  if (e === 31) return f ? NaN : s * Infinity;
  return s * Math.pow(2, e - 15) * (1 + f / 1024);
}

export function parseBuffer(arrayBuffer) {
  const bytes = new Uint8Array(arrayBuffer);
  const magic = String.fromCharCode(bytes[0], bytes[1], bytes[2], bytes[3]);
  if (magic !== "KGS1") throw new Error("not a KGS1 splat buffer");
  const dv = new DataView(arrayBuffer);
  const h = dv.getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(8, 8 + h)));
  const n = header.count;
  const base = 8 + h;
  if (header.kind === "sh") return { header, count: n, bases: header.bases, halfs: new Uint16Array(arrayBuffer.slice(base, base + 6 * n * header.bases)) };
  const positions = new Float32Array(3 * n);
  const covariances = new Float32Array(6 * n);
  const rgba = new Uint8Array(4 * n);
  const index = new Uint32Array(n);
  const scale = header.cov_scale;
  for (let i = 0; i < n; i++) {
    const o = base + i * RECORD_BYTES;
    positions[3 * i] = dv.getFloat32(o, true);
    positions[3 * i + 1] = dv.getFloat32(o + 4, true);
    positions[3 * i + 2] = dv.getFloat32(o + 8, true);
    for (let k = 0; k < 6; k++) covariances[6 * i + k] = halfToFloat(dv.getUint16(o + 12 + 2 * k, true)) * scale;
    rgba[4 * i] = bytes[o + 24]; rgba[4 * i + 1] = bytes[o + 25]; rgba[4 * i + 2] = bytes[o + 26]; rgba[4 * i + 3] = bytes[o + 27];
    index[i] = dv.getUint32(o + 28, true);
  }
  let velocity = null;
  if (header.velocity) {
    velocity = new Float32Array(3 * n);
    const vb = base + n * RECORD_BYTES;
    for (let i = 0; i < 3 * n; i++) velocity[i] = halfToFloat(dv.getUint16(vb + 2 * i, true));
  }
  return { header, count: n, positions, covariances, rgba, index, velocity };
}
