import { test } from "node:test";
import assert from "node:assert/strict";
import { nearestInTime, shakeSweep } from "../js/renderer.js";

test("the static splats' sweep is (w × x + b) over the exposure", () => {
  const shake = { t: 0.5, w: [0.3, -0.2, 0.7], b: [0.1, 0.4, -0.5] };
  const dt = 0.02, exposure = 0.5, x = [1.5, -2.0, 4.0];
  const { A, b } = shakeSweep(shake, dt, exposure);
  const [wx, wy, wz] = shake.w;
  const cross = [wy * x[2] - wz * x[1], wz * x[0] - wx * x[2], wx * x[1] - wy * x[0]];
  for (let r = 0; r < 3; r++) {
    const got = A[3 * r] * x[0] + A[3 * r + 1] * x[1] + A[3 * r + 2] * x[2] + b[r];
    assert.ok(Math.abs(got - (cross[r] + shake.b[r]) * dt * exposure) < 1e-12, `row ${r}`);
  }
});

test("the shake shown is the training frame's nearest in time", () => {
  const records = [{ t: 0.0 }, { t: 0.1 }, { t: 0.3 }];
  assert.equal(nearestInTime(records, 0.22).t, 0.3);
  assert.equal(nearestInTime(records, 0.04).t, 0.0);
  assert.equal(nearestInTime([], 0.5), null);
});
