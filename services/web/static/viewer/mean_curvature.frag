// recipes.draw_mean_curvature (§7.3.6): tone_curve(H, -1 / radius_mm, 1 / radius_mm) — convex light,
// concave dark, flat 0.5 — of the mean curvature H (eq. 7.7) of the normals smoothed at sigma_mm.
uniform float u_radius_mm;
void main() {
  float s = 1.0 / max(u_radius_mm, 1e-9);
  finish(vec3(tone_curve(texture(u_curv, v_uv).r, vec2(-s, s))));
}
