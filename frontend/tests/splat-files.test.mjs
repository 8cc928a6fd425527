import { test } from "node:test";
import assert from "node:assert/strict";
import { halfToFloat } from "../js/buffers.js";
import { covarianceOf, floatToHalf, parsePlyFile, parseSplatFile, parseSplatOrPly } from "../js/splat-files.js";

const close = (a, b, tol = 1e-5) => assert.ok(Math.abs(a - b) <= tol, `${a} vs ${b}`);

test("floatToHalf round-trips through halfToFloat", () => {
  for (const v of [0, 1, -2.5, 0.1, 1e-5, 65504, -0.000123, 3.14159]) close(halfToFloat(floatToHalf(v)), v, Math.abs(v) * 1e-3 + 1e-7);
  assert.equal(halfToFloat(floatToHalf(1e6)), 65504);
});

test("covarianceOf: a quarter turn about z swaps the x and y variances", () => {
  const c = covarianceOf([2, 1, 0.5], [Math.SQRT1_2, 0, 0, Math.SQRT1_2]);
  [1, 0, 0, 4, 0, 0.25].forEach((v, k) => close(c[k], v));
  const d = covarianceOf([1, 2, 3], [0.3, -0.2, 0.5, 0.7]);  // symmetric PSD, trace = sum of squares
  close(d[0] + d[3] + d[5], 14, 1e-4);
});

function ply(rows, names) {
  const header = `ply\nformat binary_little_endian 1.0\nelement vertex ${rows.length}\n`
    + names.map((n) => `property float ${n}\n`).join("") + "end_header\n";
  const h = new TextEncoder().encode(header);
  const buf = new ArrayBuffer(h.length + 4 * names.length * rows.length);
  new Uint8Array(buf).set(h);
  const dv = new DataView(buf);
  rows.forEach((r, i) => r.forEach((v, k) => dv.setFloat32(h.length + 4 * (i * names.length + k), v, true)));
  return buf;
}

test("a 3DGS .ply: position, covariance, colour, opacity and the SH band by coefficient", () => {
  const names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2",
    ...Array.from({ length: 9 }, (_, k) => `f_rest_${k}`), "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"];
  const rest = [0.1, 0.2, 0.3, -0.1, -0.2, -0.3, 0.5, 0.6, 0.7];  // R: 0.1 0.2 0.3, G: -0.1.., B: 0.5..
  const row = [1, 2, 3, 0, 0, 0, 0, 1, -1, ...rest, 0, Math.log(2), 0, Math.log(0.5), Math.SQRT1_2, 0, 0, Math.SQRT1_2];
  const set = parsePlyFile(ply([row, row], names));
  assert.equal(set.count, 2);
  assert.deepEqual(Array.from(set.positions.subarray(0, 3)), [1, 2, 3]);
  [1, 0, 0, 4, 0, 0.25].forEach((v, k) => close(set.covariances[k], v, 1e-5));
  assert.deepEqual(Array.from(set.rgba.subarray(0, 4)), [128, 199, 56, 128]);
  assert.equal(set.sh.bases, 3);
  // coefficient 1 (the second after DC): R 0.2, G -0.2, B 0.6
  [0.2, -0.2, 0.6].forEach((v, c) => close(halfToFloat(set.sh.halfs[3 + c]), v, 1e-3));
});

test("a .ply without splat properties, or truncated, is refused by name", () => {
  assert.throws(() => parsePlyFile(ply([[1, 2, 3]], ["x", "y", "z"])), /no opacity property/);
  const names = ["x", "y", "z", "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"];
  const buf = ply([names.map(() => 0)], names);
  assert.throws(() => parsePlyFile(buf.slice(0, buf.byteLength - 4)), /do not fit/);
  assert.throws(() => parseSplatOrPly("a.obj", buf), /drop a \.ply or \.splat/);
});

test("a .splat: 32-byte records, quaternion bytes (q - 128) / 128", () => {
  const buf = new ArrayBuffer(32), dv = new DataView(buf), u8 = new Uint8Array(buf);
  [1, 2, 3, 2, 1, 0.5].forEach((v, k) => dv.setFloat32(4 * k, v, true));
  u8.set([10, 20, 30, 40], 24);
  u8.set([128 + 91, 128, 128, 128 + 91], 28);  // about a quarter turn about z
  const set = parseSplatFile(buf);
  assert.deepEqual(Array.from(set.rgba), [10, 20, 30, 40]);
  [1, 0, 0, 4, 0, 0.25].forEach((v, k) => close(set.covariances[k], v, 2e-2));
  assert.throws(() => parseSplatFile(new ArrayBuffer(33)), /32-byte/);
});
