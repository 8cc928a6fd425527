// Shared by the browser (WebGL2, GLSL ES 3.00: frontend/js/renderer.js) and the desktop viewer
// (GLSL 3.30: app/viewer/gl_renderer.py); each prepends its #version line and its inputs.
// The rules are the CPU rasteriser's: 0.3 px^2 low-pass, quad out to the level where
// o * exp(-power) = 1/255, alpha = min(0.99, o * exp(power)).

// World to screen at camera-space centre c (c.z > 0): the view rotation W followed by the
// projection's Jacobian, rows (fx/z, 0, -fx x/z^2), (0, fy/z, -fy y/z^2); column-major.
mat3 screen_map(vec4 c, mat3 W, vec4 intr) {
  float iz = 1.0 / c.z;
  return mat3(intr.x * iz, 0.0, 0.0, 0.0, intr.y * iz, 0.0, -intr.x * c.x * iz * iz, -intr.y * c.y * iz * iz, 0.0) * W;
}

// The screen-space covariance of world covariance S under T, with the 0.3 px^2 low-pass, as
// (a, b, d, det) of [[a, b], [b, d]].
vec4 screen_covariance(mat3 T, mat3 S) {
  mat3 C2 = T * S * transpose(T);
  float a = C2[0][0] + 0.3, b = C2[0][1], d = C2[1][1] + 0.3;
  return vec4(a, b, d, a * d - b * b);
}

// The 2D footprint of a Gaussian with camera-space centre c, world covariance S, view rotation
// W, intrinsics (fx, fy, cx, cy) and opacity o. False when it cannot show. `solid` (the
// velocity-ellipse overlay) extends the quad to the whole 2-sigma ellipse.
bool splat_footprint(vec4 c, mat3 S, mat3 W, vec4 intr, float o, bool solid,
                     out vec2 center, out float r, out vec3 conic, out vec2 major) {
  if (c.z < 0.01 || o < 1.0 / 255.0) return false;
  vec4 C = screen_covariance(screen_map(c, W, intr), S);
  float a = C.x, b = C.y, d = C.z, det = C.w;
  if (det <= 0.0) return false;
  float mid = 0.5 * (a + d);
  float lam = mid + sqrt(max(0.1, mid * mid - det));
  r = ceil(sqrt(2.0 * log(255.0 * o) * lam));
  if (solid) r = max(r, ceil(2.0 * sqrt(lam)));
  float iz = 1.0 / c.z;
  center = vec2(intr.x * c.x * iz + intr.z, intr.y * c.y * iz + intr.w);
  conic = vec3(d, -b, a) / det;
  major = normalize(vec2(b, lam - a) + vec2(1e-9, 0.0));
  return true;
}

// The opacity factor that keeps a splat blurred along its sweep s (world units over the
// exposure; S already holds the blur, Σ + s sᵀ / 12) to the footprint of the sharp splat it
// averages: sqrt(1 - s2ᵀ C2⁻¹ s2 / 12) of the screen-space sweep s2 and covariance C2, as
// kgs_core/render/blur.py.
float sweep_opacity(vec4 c, mat3 S, mat3 W, vec4 intr, vec3 s) {
  if (c.z < 0.01) return 1.0;
  mat3 T = screen_map(c, W, intr);
  vec4 C = screen_covariance(T, S);
  if (C.w <= 0.0) return 1.0;
  vec2 s2 = (T * s).xy;
  float q = (C.z * s2.x * s2.x - 2.0 * C.y * s2.x * s2.y + C.x * s2.y * s2.y) / C.w;
  return sqrt(max(0.0, 1.0 - q / 12.0));
}

// Overlay colours: 1 tints static blue and dynamic orange; 2 draws the chosen dynamic splats as
// solid ellipses coloured by their screen-space major axis and dims everything else.
vec3 overlay_colour(vec3 rgb, bool dyn, bool solid, int overlay, vec2 major) {
  if (overlay == 1) return mix(rgb, dyn ? vec3(1.0, 0.55, 0.0) : vec3(0.35, 0.5, 0.85), 0.6);
  // The axis's doubled angle, so that the colour does not depend on its arbitrary sign: horizontal
  // pink, vertical blue, the two diagonals mint and violet (the legend in index.html).
  if (overlay == 2) return solid ? vec3(0.5 + 0.5 * (major.x * major.x - major.y * major.y), 0.5 + major.x * major.y, 0.9) : rgb * 0.35;
  return rgb;
}

vec4 clip_position(vec2 pix, vec2 size) {
  return vec4(2.0 * pix.x / size.x - 1.0, 1.0 - 2.0 * pix.y / size.y, 0.0, 1.0);
}
