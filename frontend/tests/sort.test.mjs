import { test } from "node:test";
import assert from "node:assert/strict";
import { depthSort } from "../js/sort.js";

function randomPositions(n, seed = 1) {
  let s = seed;
  const rnd = () => ((s = (s * 1103515245 + 12345) % 2147483648) / 2147483648);
  const p = new Float32Array(3 * n);
  for (let i = 0; i < 3 * n; i++) p[i] = rnd() * 10 - 5;
  return p;
}

test("front to back along the camera axis, behind-camera splats left out", () => {
  const p = randomPositions(5000);
  const row = [0, 0, 1, 2];  // z_cam = z + 2
  const order = depthSort(p, 5000, row);
  const z = Array.from(order, (i) => p[3 * i + 2] + 2);
  assert.ok(z.every((v) => v > 0.01));
  const visible = Array.from({ length: 5000 }, (_, i) => p[3 * i + 2] + 2).filter((v) => v > 0.01).length;
  assert.equal(order.length, visible);
  // 16-bit buckets: order is exact up to one bucket width
  const width = (Math.max(...z) - Math.min(...z)) / 65535;
  for (let k = 1; k < z.length; k++) assert.ok(z[k] >= z[k - 1] - width - 1e-6, `pair ${k}`);
});

test("each visible splat appears exactly once; ties keep index order", () => {
  const p = new Float32Array([0, 0, 1, 0, 0, 1, 0, 0, 3, 0, 0, 2, 0, 0, -1]);
  const order = depthSort(p, 5, [0, 0, 1, 0]);
  assert.deepEqual(Array.from(order), [0, 1, 3, 2]);
});

test("a rotated view sorts by the rotated depth", () => {
  const p = new Float32Array([1, 0, 0, 2, 0, 0, 3, 0, 0]);
  assert.deepEqual(Array.from(depthSort(p, 3, [-1, 0, 0, 5])), [2, 1, 0]);
  assert.deepEqual(Array.from(depthSort(p, 3, [1, 0, 0, 0])), [0, 1, 2]);
});

test("empty and all-behind inputs", () => {
  assert.equal(depthSort(new Float32Array(0), 0, [0, 0, 1, 0]).length, 0);
  assert.equal(depthSort(new Float32Array([0, 0, -5]), 1, [0, 0, 1, 0]).length, 0);
});
