// The splat fragment shader, shared by the browser and the desktop viewer (after #version).
in vec4 v_color;
in vec2 v_offset;
in vec3 v_conic;
flat in int v_solid;
out vec4 frag;
void main() {
  float power = -0.5 * (v_conic.x * v_offset.x * v_offset.x + v_conic.z * v_offset.y * v_offset.y) - v_conic.y * v_offset.x * v_offset.y;
  if (power > 0.0) discard;
  float alpha = min(0.99, v_color.a * exp(power));
  if (v_solid == 1) alpha = power > -2.0 ? 0.9 : 0.0;  // the 2-sigma ellipse
  if (alpha < 1.0 / 255.0) discard;
  frag = vec4(v_color.rgb * alpha, alpha);
}
