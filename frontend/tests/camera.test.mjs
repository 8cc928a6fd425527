import { test } from "node:test";
import assert from "node:assert/strict";
import { ORBIT_RADIANS_PER_PIXEL, OrbitCamera, cameraCenter, flyMove, focusDepth, invertRigid, lookAt, mat4Mul, orbitAtDepth, project,
  intrinsics } from "../js/camera.js";

const close = (a, b, eps = 1e-9) => a.forEach((v, i) => assert.ok(Math.abs(v - b[i]) < eps, `${i}: ${v} vs ${b[i]}`));

test("lookAt puts the target on the optical axis, up is up in the image", () => {
  const vm = lookAt([0, -3, 1], [0, 0, 0], [0, 0, 1]);
  close(cameraCenter(vm), [0, -3, 1]);
  const K = intrinsics(100, 80, 60);
  const [u, v, z] = project(vm, K, [0, 0, 0]);
  close([u, v], [50, 40]);
  assert.ok(z > 0);
  const [, vUp] = project(vm, K, [0, 0, 0.5]);
  assert.ok(vUp < 40, "a point above the target appears higher (smaller v)");
});

test("rigid inverse", () => {
  const vm = lookAt([1, 2, 3], [0, 0, 0], [0, 0, 1]);
  close(mat4Mul(vm, invertRigid(vm)), [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
});

test("orbit keeps its distance to the target and round-trips a view", () => {
  const o = new OrbitCamera([0.5, 0, 0], 2, 0.3, 0.2, [0, 0, 1]);
  for (let k = 0; k < 10; k++) {
    o.rotate(0.4, -0.1);
    const c = cameraCenter(o.viewmat());
    assert.ok(Math.abs(Math.hypot(c[0] - 0.5, c[1], c[2]) - 2) < 1e-9);
  }
  const vm = o.viewmat();
  close(OrbitCamera.fromViewmat(vm, [0.5, 0, 0], [0, 0, 1]).viewmat(), vm, 1e-9);
});

test("fly forward moves along the viewing direction", () => {
  const vm = lookAt([0, -3, 0], [0, 0, 0], [0, 0, 1]);
  close(cameraCenter(flyMove(vm, 1, 0, 0)), [0, -2, 0]);
  close(cameraCenter(flyMove(vm, 0, 1, 0)), [1, -3, 0]);
  close(cameraCenter(flyMove(vm, 0, 0, 1)), [0, -3, 1]);
});

test("focus depth is a depth quantile of the points in front; the orbit pivots there, same view", () => {
  const vm = lookAt([0, -5, 0], [0, 0, 0], [0, 0, 1]);
  // points at depths 3..7 in front, and some behind the camera that must not count
  const pts = [];
  for (const y of [-2, -1, 0, 1, 2]) pts.push(0.1 * y, y, 0.2);
  for (const y of [-8, -9, -12]) pts.push(0, y, 0);
  assert.ok(Math.abs(focusDepth(vm, new Float32Array(pts), pts.length / 3) - 4) < 1e-5);  // lower quartile
  const depth = focusDepth(vm, new Float32Array(pts), pts.length / 3, 0.5);
  assert.ok(Math.abs(depth - 5) < 1e-5, `${depth}`);
  assert.equal(focusDepth(vm, new Float32Array([0, -9, 0]), 1), null);
  const o = orbitAtDepth(vm, depth, [0, 0, 1]);
  close(o.viewmat(), vm, 1e-6);  // the same view...
  close(o.target, [0, 0, 0], 1e-6);  // ...turning about the content, which stays centred
  const K = intrinsics(900, 600, 60);
  o.rotate(-ORBIT_RADIANS_PER_PIXEL * 200, 0);  // a 200 px drag
  const [u, v] = project(o.viewmat(), K, [0, 0, 0]);
  close([u, v], [450, 300], 1e-6);
  const turned = Math.acos(o.viewmat()[8] * vm[8] + o.viewmat()[9] * vm[9] + o.viewmat()[10] * vm[10]) * 180 / Math.PI;
  assert.ok(turned > 10 && turned < 25, `a 200 px drag turned ${turned} degrees`);
});
