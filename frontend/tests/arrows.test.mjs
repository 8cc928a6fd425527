import { test } from "node:test";
import assert from "node:assert/strict";
import { arrowScale, arrowSegments } from "../js/arrows.js";

test("arrowSegments draws a shaft and a two-stroke head per arrow, facing the camera", () => {
  const seg = arrowSegments([0, 0, 0], [1, 0, 0], 1, 1, 2, [0, 0, 1]);
  assert.equal(seg.length, 3 * 2 * 4);  // three segments of two [x, y, z, w] vertices
  assert.deepEqual([...seg.slice(0, 8)], [0, 0, 0, 0, 2, 0, 0, 1]);
  const heads = [[...seg.slice(12, 15)], [...seg.slice(20, 23)]];
  for (const h of heads) {
    assert.ok(Math.abs(h[0] - 1.5) < 1e-6 && Math.abs(Math.abs(h[1]) - 0.25) < 1e-6 && h[2] === 0);
  }
  assert.ok(heads[0][1] * heads[1][1] < 0);  // one stroke each side
  assert.equal(arrowSegments([0, 0, 0], [0, 0, 0], 1, 1, 2, [0, 0, 1]).length, 0);  // still: no arrow
});

test("arrowScale lengthens sub-pixel motion to a visible arrow, never below three frames", () => {
  const pos = [0, 0, 0, 1, 0, 0], dt = 0.01;
  const [slow, framesSlow] = arrowScale(pos, [1e-4, 0, 0, 1e-4, 0, 0], 2, dt);
  assert.ok(Math.abs(slow * 1e-4 - 0.05) < 1e-9 && framesSlow > 3);  // 5 % of the extent
  const [, framesFast] = arrowScale(pos, [100, 0, 0, 100, 0, 0], 2, dt);
  assert.equal(framesFast, 3);
});
