import { test } from "node:test";
import assert from "node:assert/strict";
import { frontOf } from "../js/pick.js";

// [index, u, v, depth]
const ball = [[1, 10, 10, 2.0], [2, 12, 11, 2.2], [3, 20, 14, 2.1]];  // its far side too (2.2)
const wall = [[10, 11, 10, 3.0], [11, 19, 15, 3.1], [12, 40, 40, 3.0]];  // behind it, and beside it

test("frontOf keeps the surface in front and drops what lies behind it", () => {
  const kept = frontOf([...ball, ...wall]).map((h) => h[0]).sort((a, b) => a - b);
  assert.deepEqual(kept, [1, 2, 3, 12]);  // the wall beside the ball is the front there
});

test("frontOf keeps everything when nothing overlaps, and nothing from nothing", () => {
  assert.equal(frontOf(wall).length, wall.length);
  assert.deepEqual(frontOf([]), []);
});

test("frontOf hides a hit behind a nearer splat that lies outside the hits", () => {
  // A box that takes only the wall splat at (11, 10): the ball splat beside it is drawn in front.
  const inBox = [wall[0]];
  assert.deepEqual(frontOf(inBox, [...ball, ...wall]), []);
  assert.deepEqual(frontOf(inBox).map((h) => h[0]), [10]);  // judged among the hits alone, it showed
});
