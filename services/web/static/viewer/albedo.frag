// recipes.draw_albedo: the colour, its CIELAB lightness exposed (u_exposure.x < 0: as captured).
uniform vec2 u_exposure;
void main() { finish(exposed_colour(u_exposure)); }
