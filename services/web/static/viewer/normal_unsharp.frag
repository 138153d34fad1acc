// recipes.draw_normal_unsharp / enhance.normal_unsharp_masking (RTIViewer; Malzbender et al. 2006):
// n_e = normalize(n + gain (n - G_sigma n)), shade = max(n_e . l, 0); grey: tone_curve(shade, exposure);
// colour: RTIViewer's picture (colour x shade) with its lightness exposed.
uniform float u_gain;
uniform vec2 u_exposure;
uniform bool u_colour_on;
void main() {
  vec3 n = normal_n();
  vec3 e = n + u_gain * (n - normal_nu());
  e /= max(length(e), 1e-12);
  float shade = max(dot(e, u_light), 0.0);
  if (u_colour_on) {
    vec3 lit = srgb_to_linear(display_albedo() * shade);
    finish(lightness_relief(lit, 0.0, 0.0, u_exposure));
  } else {
    finish(vec3(tone_curve(shade, u_exposure)));
  }
}
