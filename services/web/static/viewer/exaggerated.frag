// recipes.draw_exaggerated / shading.exaggerated_shading (Rusinkiewicz, Burns & DeCarlo 2006), with
// scales = 3 (n0..n3 at sigma_px * 2^i): c_i = clamp(contrast n_i . l_{i+1}, -1, 1) with l_{i+1} the light
// projected into the tangent plane of n_{i+1}; weights k_i = sigma_i^-detail normalised; the base adds
// base_weight clamp(contrast n3 . l). d = 0.5 (sum) / (1 + base_weight); grey: tone_curve(d, tones);
// colour: the tone as relief on the colour's lightness (strength, exposure).
uniform float u_contrast;
uniform float u_detail;
uniform float u_base_weight;
uniform vec2 u_tones;
uniform bool u_colour_on;
uniform float u_strength;
uniform vec2 u_exposure;
float term(vec3 nf, vec3 nc) {
  float lc = dot(nc, u_light);
  float c = dot(nf, u_light) - lc * dot(nf, nc);
  c /= sqrt(max(1.0 - lc * lc, 1e-8));
  return clamp(u_contrast * c, -1.0, 1.0);
}
void main() {
  vec3 n0 = normal_n0(), n1 = normal_n1(), n2 = normal_n2(), n3 = normal_n3();
  // k_i = sigma_i^-detail with sigma_i = sigma_px 2^i: the ratios do not depend on sigma_px
  float k0 = 1.0, k1 = pow(2.0, -u_detail), k2 = pow(4.0, -u_detail);
  float ks = k0 + k1 + k2;
  float total = (k0 * term(n0, n1) + k1 * term(n1, n2) + k2 * term(n2, n3)) / ks;
  if (u_base_weight > 0.0) total += u_base_weight * clamp(u_contrast * dot(n3, u_light), -1.0, 1.0);
  float d = 0.5 * total / (1.0 + u_base_weight);
  float tone = tone_curve(d, u_tones);
  if (u_colour_on) finish(lightness_relief(albedo(), 2.0 * tone - 1.0, u_strength, u_exposure));
  else finish(vec3(tone));
}
