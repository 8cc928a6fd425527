// Velocity arrows as line segments, with heads (no DOM: unit-tested under node,
// frontend/tests/arrows.test.mjs). Each vertex is [x, y, z, w], w = 0 at the tail, 1 on the head.

const HEAD = 0.25;  // head length, as a fraction of the arrow
const MIN_FRAMES = 3;  // an arrow spans at least three frame intervals of motion

// The factor from velocity (scene units per unit time) to arrow length: at least MIN_FRAMES
// frame intervals, and enough that the 90th-percentile arrow is 5 % of the dynamic set's
// extent (sub-pixel motion otherwise drew 1-6 px dashes). Returns [factor, frame intervals].
export function arrowScale(positions, velocity, count, dt) {
  if (!count) return [MIN_FRAMES * dt, MIN_FRAMES];
  const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
  const speeds = new Float64Array(count);
  for (let i = 0; i < count; i++) {
    for (let k = 0; k < 3; k++) {
      lo[k] = Math.min(lo[k], positions[3 * i + k]);
      hi[k] = Math.max(hi[k], positions[3 * i + k]);
    }
    speeds[i] = Math.hypot(velocity[3 * i], velocity[3 * i + 1], velocity[3 * i + 2]);
  }
  speeds.sort();
  const p90 = speeds[Math.min(count - 1, Math.floor(0.9 * count))];
  const extent = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
  const frames = p90 > 0 ? Math.max(MIN_FRAMES, (0.05 * extent) / (p90 * dt)) : MIN_FRAMES;
  return [frames * dt, frames];
}

// Segments for every `step`-th splat: the shaft and two head strokes, drawn in the plane that
// faces `forward` (the camera's viewing direction), so the head reads from where it is seen.
export function arrowSegments(positions, velocity, count, step, scale, forward) {
  const out = [];
  for (let i = 0; i < count; i += step) {
    const p = [positions[3 * i], positions[3 * i + 1], positions[3 * i + 2]];
    const d = [scale * velocity[3 * i], scale * velocity[3 * i + 1], scale * velocity[3 * i + 2]];
    const len = Math.hypot(d[0], d[1], d[2]);
    if (!(len > 0)) continue;
    const q = [p[0] + d[0], p[1] + d[1], p[2] + d[2]];
    out.push(...p, 0, ...q, 1);
    // side = d x forward, normalised; along d when the arrow points at the camera
    let s = [d[1] * forward[2] - d[2] * forward[1], d[2] * forward[0] - d[0] * forward[2], d[0] * forward[1] - d[1] * forward[0]];
    const sl = Math.hypot(s[0], s[1], s[2]);
    if (!(sl > 1e-12)) continue;
    s = s.map((v) => v / sl);
    for (const sign of [1, -1]) {
      const h = [0, 1, 2].map((k) => q[k] - HEAD * d[k] + sign * 0.5 * HEAD * len * s[k]);
      out.push(...q, 1, ...h, 1);
    }
  }
  return new Float32Array(out);
}
