// Camera math in the product's convention (OpenCV: x right, y down, z forward), with
// world-to-camera 4x4 matrices stored row-major as arrays of 16 numbers.

export function mat4Mul(a, b) {
  const o = new Array(16).fill(0);
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[4 * r + k] * b[4 * k + c];
    o[4 * r + c] = s;
  }
  return o;
}

export function invertRigid(m) {
  // inverse of [R t; 0 1] = [R^T -R^T t; 0 1]
  const R = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
  const t = [m[3], m[7], m[11]];
  const o = [R[0], R[3], R[6], 0, R[1], R[4], R[7], 0, R[2], R[5], R[8], 0, 0, 0, 0, 1];
  for (let i = 0; i < 3; i++) o[4 * i + 3] = -(o[4 * i] * t[0] + o[4 * i + 1] * t[1] + o[4 * i + 2] * t[2]);
  return o;
}

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
export const vec = { sub, cross, norm };

// World-to-camera for a camera at `eye` looking at `target`; `up` is the world direction
// shown up in the image.
export function lookAt(eye, target, up) {
  const z = norm(sub(target, eye));
  let x = cross([-up[0], -up[1], -up[2]], z);
  if (Math.hypot(...x) < 1e-9) x = cross([1, 0, 0], z);
  x = norm(x);
  const y = cross(z, x);
  const R = [x, y, z];
  const t = R.map((r) => -(r[0] * eye[0] + r[1] * eye[1] + r[2] * eye[2]));
  return [x[0], x[1], x[2], t[0], y[0], y[1], y[2], t[1], z[0], z[1], z[2], t[2], 0, 0, 0, 1];
}

export function cameraCenter(viewmat) {
  const inv = invertRigid(viewmat);
  return [inv[3], inv[7], inv[11]];
}

// Pixel coordinates (u, v) and depth of a world point.
export function project(viewmat, K, p) {
  const x = viewmat[0] * p[0] + viewmat[1] * p[1] + viewmat[2] * p[2] + viewmat[3];
  const y = viewmat[4] * p[0] + viewmat[5] * p[1] + viewmat[6] * p[2] + viewmat[7];
  const z = viewmat[8] * p[0] + viewmat[9] * p[1] + viewmat[10] * p[2] + viewmat[11];
  return [K[0] * x / z + K[2], K[4] * y / z + K[5], z];
}

// Orbit: the camera circles `target` at `distance`, yaw about `up`, pitch toward it.
export class OrbitCamera {
  constructor(target, distance, yaw, pitch, up = [0, 0, 1]) {
    Object.assign(this, { target, distance, yaw, pitch, up: norm(up) });
  }
  static fromViewmat(viewmat, target, up) {
    const c = cameraCenter(viewmat);
    const d = sub(c, target);
    const dist = Math.hypot(...d);
    const u = norm(up);
    const h = d[0] * u[0] + d[1] * u[1] + d[2] * u[2];
    const pitch = Math.asin(Math.max(-1, Math.min(1, h / dist)));
    const e1 = OrbitCamera.basis(u)[0], e2 = cross(u, e1);
    const yaw = Math.atan2(d[0] * e2[0] + d[1] * e2[1] + d[2] * e2[2], d[0] * e1[0] + d[1] * e1[1] + d[2] * e1[2]);
    return new OrbitCamera(target, dist, yaw, pitch, u);
  }
  static basis(u) {
    const a = Math.abs(u[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
    const e1 = norm(cross(cross(u, a), u));
    return [e1, cross(u, e1)];
  }
  eye() {
    const [e1, e2] = OrbitCamera.basis(this.up);
    const cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const dir = [0, 1, 2].map((i) => cp * (Math.cos(this.yaw) * e1[i] + Math.sin(this.yaw) * e2[i]) + sp * this.up[i]);
    return [0, 1, 2].map((i) => this.target[i] + this.distance * dir[i]);
  }
  viewmat() { return lookAt(this.eye(), this.target, this.up); }
  rotate(dyaw, dpitch) {
    this.yaw += dyaw;
    this.pitch = Math.max(-1.5, Math.min(1.5, this.pitch + dpitch));
  }
  zoom(factor) { this.distance = Math.max(1e-3, this.distance * factor); }
  pan(dx, dy) {
    const vm = this.viewmat();
    const right = [vm[0], vm[1], vm[2]], down = [vm[4], vm[5], vm[6]];
    const s = this.distance;
    this.target = [0, 1, 2].map((i) => this.target[i] - s * (dx * right[i] + dy * down[i]));
  }
}

// Radians the orbit turns per pixel dragged, either way: 200 px turn the view about 20 degrees,
// whatever the canvas's size.
export const ORBIT_RADIANS_PER_PIXEL = 0.0017;

// A depth quantile, along the camera's optical axis, of the points in front of it: where the
// scene's content starts, and so where an orbit should pivot to keep it in frame. null when no
// point is in front. `positions` holds x, y, z per point; at most `sample` points are read.
// The lower quartile, not the median: in a corridor or a room filmed from inside, turning about
// the median depth swings the camera through the near walls.
export function focusDepth(viewmat, positions, count, quantile = 0.25, sample = 20000) {
  const step = Math.max(1, Math.floor(count / sample));
  const depths = [];
  for (let i = 0; i < count; i += step) {
    const z = viewmat[8] * positions[3 * i] + viewmat[9] * positions[3 * i + 1] + viewmat[10] * positions[3 * i + 2]
      + viewmat[11];
    if (z > 1e-6) depths.push(z);
  }
  if (!depths.length) return null;
  depths.sort((a, b) => a - b);
  return depths[Math.min(depths.length - 1, Math.floor(quantile * depths.length))];
}

// The same view, orbiting about the point `depth` ahead of the camera.
export function orbitAtDepth(viewmat, depth, up) {
  const c = cameraCenter(viewmat);
  const target = [0, 1, 2].map((i) => c[i] + depth * viewmat[8 + i]);
  return OrbitCamera.fromViewmat(viewmat, target, up);
}

// Fly: WASD moves along the camera axes; mouse turns.
export function flyMove(viewmat, forward, right, upward) {
  const inv = invertRigid(viewmat);
  for (let i = 0; i < 3; i++) {
    inv[4 * i + 3] += forward * inv[4 * i + 2] + right * inv[4 * i] - upward * inv[4 * i + 1];
  }
  return invertRigid(inv);
}

export function flyTurn(viewmat, yaw, pitch) {
  // rotate the camera about its own y (yaw) and x (pitch) axes
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const Ry = [cy, 0, -sy, 0, 0, 1, 0, 0, sy, 0, cy, 0, 0, 0, 0, 1];
  const Rx = [1, 0, 0, 0, 0, cp, sp, 0, 0, -sp, cp, 0, 0, 0, 0, 1];
  return mat4Mul(mat4Mul(Rx, Ry), viewmat);
}

export function intrinsics(width, height, fovXDeg = 60) {
  const fx = 0.5 * width / Math.tan((fovXDeg * Math.PI) / 360);
  return [fx, 0, width / 2, 0, fx, height / 2, 0, 0, 1];
}
