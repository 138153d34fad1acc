// Shared by every style shader (prepended after "#version 300 es" by viewer.js). The formulas
// mirror common/render/_util.py, enhance.py and common/rgbn/io.py of the offline renderer.
precision highp float;
in vec2 v_uv;
out vec4 outColor;

uniform sampler2D u_n01;     // (x, y) of n (as solved) | n0 (smoothed at the noise scale sigma_px)
uniform sampler2D u_n23;     // n1 (2 sigma_px) | n2 (4 sigma_px)
uniform sampler2D u_n3u;     // n3 (8 sigma_px) | nu (normal unsharp masking's sigma_mm)
uniform sampler2D u_curv;    // mean curvature H, 1/mm
uniform sampler2D u_colour;  // display sRGB albedo, mask in alpha
uniform vec3 u_light;        // unit light direction, x right, y up, z towards the viewer
uniform vec3 u_background;   // display RGB outside the fragment

// a unit normal from its (x, y): z = sqrt(1 - x^2 - y^2), towards the viewer
vec3 unit(vec2 xy) { return vec3(xy, sqrt(max(1.0 - dot(xy, xy), 0.0))); }
vec3 normal_n()  { return unit(texture(u_n01, v_uv).xy); }
vec3 normal_n0() { return unit(texture(u_n01, v_uv).zw); }
vec3 normal_n1() { return unit(texture(u_n23, v_uv).xy); }
vec3 normal_n2() { return unit(texture(u_n23, v_uv).zw); }
vec3 normal_n3() { return unit(texture(u_n3u, v_uv).xy); }
vec3 normal_nu() { return unit(texture(u_n3u, v_uv).zw); }
bool on_fragment() { return texture(u_colour, v_uv).a >= 0.5; }

// IEC 61966-2-1 (common.rgbn.io.srgb_to_linear / linear_to_srgb), clipped to [0, 1] first
vec3 srgb_to_linear(vec3 v) {
  v = clamp(v, 0.0, 1.0);
  return mix(pow((v + 0.055) / 1.055, vec3(2.4)), v / 12.92, vec3(lessThanEqual(v, vec3(0.04045))));
}
vec3 linear_to_srgb(vec3 v) {
  v = clamp(v, 0.0, 1.0);
  return mix(1.055 * pow(v, vec3(1.0 / 2.4)) - 0.055, v * 12.92, vec3(lessThanEqual(v, vec3(0.0031308))));
}
// the display albedo (common.render._util.display_albedo) and the linear albedo
vec3 display_albedo() { return texture(u_colour, v_uv).rgb; }
vec3 albedo() { return srgb_to_linear(texture(u_colour, v_uv).rgb); }

// enhance.tone_curve: 0.5 + 0.5 tanh(k (v - (lo + hi) / 2)), k = atanh(0.6) / ((hi - lo) / 2)
float tone_curve(float v, vec2 range) {
  if (!(range.y > range.x)) return 0.5;
  float k = 0.6931471805599453 / (0.5 * (range.y - range.x));
  return 0.5 + 0.5 * tanh(k * (v - 0.5 * (range.x + range.y)));
}
// enhance.shoulder: identity below the knee, then a tanh roll-off towards 1
vec3 shoulder(vec3 v, float knee) {
  float room = 1.0 - knee;
  return mix(v, knee + room * tanh((v - knee) / room), vec3(greaterThan(v, vec3(knee))));
}

// CIELAB as OpenCV's float COLOR_LRGB2Lab / COLOR_Lab2RGB (D65, sRGB primaries)
float lab_f(float t) { return t > 0.008856 ? pow(t, 1.0 / 3.0) : 7.787 * t + 16.0 / 116.0; }
vec3 linear_to_lab(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  float X = (0.412453 * c.r + 0.357580 * c.g + 0.180423 * c.b) / 0.950456;
  float Y =  0.212671 * c.r + 0.715160 * c.g + 0.072169 * c.b;
  float Z = (0.019334 * c.r + 0.119193 * c.g + 0.950227 * c.b) / 1.088754;
  float fy = lab_f(Y);
  float L = Y > 0.008856 ? 116.0 * fy - 16.0 : 903.3 * Y;
  return vec3(L, 500.0 * (lab_f(X) - fy), 200.0 * (fy - lab_f(Z)));
}
float lab_finv(float f) { return f > 0.206893 ? f * f * f : (f - 16.0 / 116.0) / 7.787; }
// enhance.lab_to_linear_rgb: CIELAB to linear sRGB with OpenCV's constants, NOT clipped
vec3 lab_to_linear(vec3 lab) {
  float fy, Y;
  if (lab.x <= 7.9996) { Y = lab.x / 903.3; fy = 7.787 * Y + 16.0 / 116.0; }
  else { fy = (lab.x + 16.0) / 116.0; Y = fy * fy * fy; }
  float X = lab_finv(lab.y / 500.0 + fy) * 0.950456;
  float Z = lab_finv(fy - lab.z / 200.0) * 1.088754;
  return vec3( 3.240479 * X - 1.537150 * Y - 0.498535 * Z,
              -0.969256 * X + 1.875991 * Y + 0.041556 * Z,
               0.055648 * X - 0.204043 * Y + 1.057311 * Z);
}
bool in_gamut(vec3 c, float eps) { return all(greaterThanEqual(c, vec3(-eps))) && all(lessThanEqual(c, vec3(1.0 + eps))); }
// enhance.gamut_map_lab + _into_gamut: a colour sRGB cannot show keeps its L* and hue, its chroma
// scaled by the largest s in [0, 1] that fits (GAMUT_STEPS = 16 bisection steps), then sRGB-encoded
vec3 lab_to_srgb(vec3 lab) {
  lab.x = clamp(lab.x, 0.0, 100.0);
  vec3 rgb = lab_to_linear(lab);
  if (!in_gamut(rgb, 1e-5)) {
    float lo = 0.0, hi = 1.0;
    for (int i = 0; i < 16; i++) {
      float mid = 0.5 * (lo + hi);
      if (in_gamut(lab_to_linear(vec3(lab.x, mid * lab.yz)), 0.0)) lo = mid; else hi = mid;
    }
    rgb = lab_to_linear(vec3(lab.x, lo * lab.yz));
  }
  return linear_to_srgb(rgb);
}
// enhance.lightness_relief: relief in [-1, 1] as a soft-light on L* only; exposure.x < 0 = none
vec3 lightness_relief(vec3 lin, float relief, float strength, vec2 exposure) {
  vec3 lab = linear_to_lab(lin);
  float L = lab.x;
  if (exposure.x >= 0.0 && exposure.y > exposure.x) {
    float L2 = 100.0 * tone_curve(L, exposure);
    float k = clamp(L2 / max(L, 1.0), 0.0, 2.0);
    lab.yz *= k;
    L = L2;
  }
  float r = clamp(relief, -1.0, 1.0) * strength;
  L = L + r * (r > 0.0 ? 100.0 - L : L);
  lab.x = L;
  return lab_to_srgb(lab);
}
// recipes._exposed_colour: the display colour with its lightness exposed (exposure.x < 0: as captured)
vec3 exposed_colour(vec2 exposure) {
  if (exposure.x < 0.0) return display_albedo();
  return lightness_relief(albedo(), 0.0, 0.0, exposure);
}
void finish(vec3 rgb) {
  outColor = vec4(on_fragment() ? rgb : u_background, 1.0);
}
