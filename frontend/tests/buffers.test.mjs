import { test } from "node:test";
import assert from "node:assert/strict";
import { halfToFloat, parseBuffer } from "../js/buffers.js";
import { packSet, unpackSplat, textureRows, WORDS_PER_SPLAT, FLAG_DYNAMIC, FLAG_SELECTED } from "../js/pack.js";

// float32 -> float16 bits (round to nearest), independent of the parser under test
function toHalf(v) {
  const f = new Float32Array([v]), u = new Uint32Array(f.buffer)[0];
  const sign = (u >> 16) & 0x8000, exp = ((u >> 23) & 0xff) - 127 + 15, mant = u & 0x7fffff;
  if (exp <= 0) return sign | Math.round((mant | 0x800000) / 2 ** (14 - exp));
  return sign | (exp << 10) | Math.round(mant / 8192);
}

function makeBuffer(records, { velocity = null, covScale = 1e-4 } = {}) {
  let header = JSON.stringify({ kind: "dynamic", count: records.length, cov_scale: covScale, velocity: !!velocity, t: 0.5 });
  while (header.length % 4) header += " ";
  const n = records.length;
  const size = 8 + header.length + 32 * n + (velocity ? Math.ceil((6 * n) / 4) * 4 : 0);
  const buf = new ArrayBuffer(size);
  const dv = new DataView(buf), u8 = new Uint8Array(buf);
  u8.set([75, 71, 83, 49], 0);
  dv.setUint32(4, header.length, true);
  u8.set(new TextEncoder().encode(header), 8);
  const base = 8 + header.length;
  records.forEach((r, i) => {
    const o = base + 32 * i;
    r.p.forEach((v, k) => dv.setFloat32(o + 4 * k, v, true));
    r.c.forEach((v, k) => dv.setUint16(o + 12 + 2 * k, toHalf(v / covScale), true));
    u8.set(r.rgba, o + 24);
    dv.setUint32(o + 28, r.index, true);
  });
  if (velocity) velocity.forEach((v, k) => dv.setUint16(base + 32 * n + 2 * k, toHalf(v), true));
  return buf;
}

test("half floats decode", () => {
  assert.equal(halfToFloat(0x3c00), 1);
  assert.equal(halfToFloat(0xc000), -2);
  assert.equal(halfToFloat(0x7bff), 65504);
  assert.equal(halfToFloat(0x0001), 2 ** -24);
  assert.equal(halfToFloat(toHalf(0.1)), 0.0999755859375);
});

test("a buffer parses into positions, covariances, colours, indices, velocities", () => {
  const recs = [
    { p: [1.5, -2, 3.25], c: [4e-4, 1e-5, 0, 2e-4, -3e-5, 1e-4], rgba: [255, 128, 0, 200], index: 7 },
    { p: [0, 0, 0], c: [1e-3, 0, 0, 1e-3, 0, 1e-3], rgba: [1, 2, 3, 4], index: 123456 },
  ];
  const set = parseBuffer(makeBuffer(recs, { velocity: [1, -0.5, 0.25, 0, 2, 0] }));
  assert.equal(set.count, 2);
  assert.equal(set.header.kind, "dynamic");
  assert.deepEqual(Array.from(set.positions), [1.5, -2, 3.25, 0, 0, 0]);
  recs.forEach((r, i) => r.c.forEach((v, k) => assert.ok(Math.abs(set.covariances[6 * i + k] - v) <= 1e-3 * Math.abs(v) + 1e-12)));
  assert.deepEqual(Array.from(set.rgba), [255, 128, 0, 200, 1, 2, 3, 4]);
  assert.deepEqual(Array.from(set.index), [7, 123456]);
  assert.deepEqual(Array.from(set.velocity), [1, -0.5, 0.25, 0, 2, 0]);
  assert.throws(() => parseBuffer(new ArrayBuffer(16)), /KGS1/);
});

test("packing into the texture and back", () => {
  const recs = Array.from({ length: 1500 }, (_, i) => ({ p: [i, -i, i / 2], c: [1e-3, 2e-4, 0, 1e-3, 0, 5e-4], rgba: [i % 256, 1, 2, 255], index: 10 * i }));
  const set = parseBuffer(makeBuffer(recs));
  const rows = textureRows(1500 + 10);
  assert.equal(rows, 2);
  const words = new Uint32Array(rows * 3072 * 4);
  packSet(words, 10, set, FLAG_DYNAMIC, new Set([20]));
  const s = unpackSplat(words, 12);
  assert.deepEqual(s.position, [2, -2, 1]);
  assert.equal(s.index, 20);
  assert.equal(s.flags, FLAG_DYNAMIC | FLAG_SELECTED);
  assert.deepEqual(s.rgba, [2, 1, 2, 255]);
  assert.ok(Math.abs(s.covariance[0] - 1e-3) < 1e-6);
  assert.equal(unpackSplat(words, 13).flags, FLAG_DYNAMIC);
  assert.equal(WORDS_PER_SPLAT, 12);
});
