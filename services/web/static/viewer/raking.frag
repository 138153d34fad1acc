// recipes.draw_raking: Lambertian shading from a low light (the light is set by azimuth_deg,
// elevation_deg in viewer.js); the formula is draw_lambertian's.
uniform float u_ambient;
uniform vec2 u_exposure;
uniform bool u_colour_on;
uniform vec2 u_colour_exposure;
void main() {
  float shade = u_ambient + (1.0 - u_ambient) * max(dot(normal_n0(), u_light), 0.0);
  if (u_colour_on) {
    float relief = 2.0 * tone_curve(shade, u_exposure) - 1.0;
    finish(lightness_relief(albedo(), relief, 0.8, u_colour_exposure));
  } else {
    finish(vec3(tone_curve(shade, u_exposure)));
  }
}
