import { test } from "node:test";
import assert from "node:assert/strict";
import { OrbitCamera, cameraCenter, flyMove, invertRigid, lookAt, mat4Mul, project, intrinsics } from "../js/camera.js";

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
