// recipes.draw_lambertian / shading.lambertian (§7.3.1): shade = ambient + (1 - ambient) max(0, n0 . l)
// on the normals smoothed at the noise scale; grey: tone_curve(shade, exposure); colour: the shade's
// tone as relief on the colour's lightness (strength 0.8, colour_exposure).
uniform float u_ambient;
uniform vec2 u_exposure;
uniform bool u_colour_on;
uniform vec2 u_colour_exposure;   // x < 0: "none"
void main() {
  float shade = u_ambient + (1.0 - u_ambient) * max(dot(normal_n0(), u_light), 0.0);
  if (u_colour_on) {
    float relief = 2.0 * tone_curve(shade, u_exposure) - 1.0;
    finish(lightness_relief(albedo(), relief, 0.8, u_colour_exposure));
  } else {
    finish(vec3(tone_curve(shade, u_exposure)));
  }
}
