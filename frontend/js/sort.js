// Depth sort for front-to-back blending: a 16-bit single-pass counting sort on camera-space
// depth (as antimatter15/splat does), stable for equal keys. Re-run whenever the camera moves
// or the time changes (dynamic splats move; sorting on time-0 centres is a known bug of 4D
// players).

// viewRow: the third row of the world-to-camera matrix [r20, r21, r22, t2] (OpenCV: z forward).
// Returns a Uint32Array of splat indices, nearest first, leaving out splats behind the camera.
export function depthSort(positions, count, viewRow, near = 0.01) {
  const depth = new Float32Array(count);
  let min = Infinity, max = -Infinity, visible = 0;
  for (let i = 0; i < count; i++) {
    const z = viewRow[0] * positions[3 * i] + viewRow[1] * positions[3 * i + 1] + viewRow[2] * positions[3 * i + 2] + viewRow[3];
    depth[i] = z;
    if (z > near) {
      visible++;
      if (z < min) min = z;
      if (z > max) max = z;
    }
  }
  const out = new Uint32Array(visible);
  if (visible === 0) return out;
  const BUCKETS = 65536;
  const scale = max > min ? (BUCKETS - 1) / (max - min) : 0;
  const keys = new Uint16Array(count);
  const counts = new Uint32Array(BUCKETS);
  for (let i = 0; i < count; i++) {
    if (depth[i] > near) {
      const k = ((depth[i] - min) * scale) | 0;
      keys[i] = k;
      counts[k]++;
    }
  }
  let sum = 0;
  for (let k = 0; k < BUCKETS; k++) { const c = counts[k]; counts[k] = sum; sum += c; }
  for (let i = 0; i < count; i++) if (depth[i] > near) out[counts[keys[i]]++] = i;
  return out;
}
