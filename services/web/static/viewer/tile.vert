#version 300 es
// One tile as a screen-space quad. u_rect: the tile's corners in canvas pixels (x0, y0, x1, y1,
// y down); u_canvas: the canvas size in pixels. v_uv: texture coordinates (0,0 = the tile's first
// stored row and column, which is the top-left pixel of the tile).
in vec2 a_corner;
uniform vec4 u_rect;
uniform vec2 u_canvas;
out vec2 v_uv;
void main() {
  vec2 p = mix(u_rect.xy, u_rect.zw, a_corner);
  v_uv = a_corner;
  gl_Position = vec4(p.x / u_canvas.x * 2.0 - 1.0, 1.0 - p.y / u_canvas.y * 2.0, 0.0, 1.0);
}
