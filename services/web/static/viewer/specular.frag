// recipes.draw_specular / enhance.specular_enhancement (Malzbender et al. 2001):
// I = kd base max(n0 . l, 0) + ks max(n0 . h, 0)^exponent, h = normalize(l + v), v = (0, 0, 1);
// then divided by the exposure's high end and rolled off above 0.8 (enhance.shoulder), then its
// lightness exposed (recipes._exposed_lightness; u_lightness.x < 0: as drawn).
uniform float u_kd;
uniform float u_ks;
uniform float u_exponent;
uniform vec2 u_exposure;
uniform bool u_colour_on;
uniform vec2 u_colour_exposure;
uniform vec2 u_lightness;
void main() {
  vec3 n = normal_n0();
  vec3 h = normalize(u_light + vec3(0.0, 0.0, 1.0));
  float diffuse = max(dot(n, u_light), 0.0) * u_kd;
  float spec = u_ks * pow(max(dot(n, h), 0.0), u_exponent);
  vec3 base = u_colour_on ? exposed_colour(u_colour_exposure) : vec3(0.75);
  vec3 lit = base * diffuse + spec;
  vec3 drawn = shoulder(lit / max(u_exposure.y, 1e-6), 0.8);
  if (u_lightness.x >= 0.0) drawn = lightness_relief(srgb_to_linear(drawn), 0.0, 0.0, u_lightness);
  finish(drawn);
}
