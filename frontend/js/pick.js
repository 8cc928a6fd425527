// Selection helpers with no DOM or WebGL (unit-tested under node: frontend/tests/pick.test.mjs).

// The hits (`[index, u, v, depth]`) on the visible surface: a coarse depth buffer of the
// nearest centre per FRONT_CELL-pixel cell, widened to each cell's 3x3 neighbourhood (centres
// are sparser than pixels), keeps those within FRONT_DEPTH of it (relative), so the far side
// of a selected object stays selected and what lies behind it does not. The depth buffer is
// built from `drawn` (every splat on screen, by default the hits), so that a splat at a box's
// edge is hidden by a nearer one just outside the box as it is inside a larger box.
const FRONT_CELL = 6;
const FRONT_DEPTH = 0.15;

export function frontOf(hits, drawn = hits) {
  const near = new Map();
  const key = (cx, cy) => `${cx},${cy}`;
  for (const h of drawn) {
    const k = key(Math.floor(h[1] / FRONT_CELL), Math.floor(h[2] / FRONT_CELL));
    if (!(near.get(k) <= h[3])) near.set(k, h[3]);
  }
  return hits.filter((h) => {
    const cx = Math.floor(h[1] / FRONT_CELL), cy = Math.floor(h[2] / FRONT_CELL);
    let zmin = Infinity;
    for (let dx = -1; dx <= 1; dx++) for (let dy = -1; dy <= 1; dy++) {
      const z = near.get(key(cx + dx, cy + dy));
      if (z !== undefined && z < zmin) zmin = z;
    }
    return h[3] <= zmin * (1 + FRONT_DEPTH);
  });
}
