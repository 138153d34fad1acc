import functools

import numpy as np
import pytest

from common.render.recipes import (RECIPE_DIR, STYLES, load_recipe, parse_recipe, recipe_to_toml, render,
                                   style_recipe)
from common.rgbn.image import RGBNImage
from tests.rgbn.analytic import gaussian_bump, sphere, tilted_plane


@pytest.fixture(scope="module")
def fragment():
    """A small fragment: a bump on a plate, two colours, a round outline."""
    n = gaussian_bump(72, 0.1, 0.8, 0.8)
    _, mask = sphere(72, 3.4, 0.1, fill=1.0)
    albedo = np.full((72, 72, 3), 0.6, np.float32)
    albedo[:, 36:] = (0.5, 0.25, 0.15)
    return RGBNImage(albedo=albedo, mask=mask, dpi=254.0, normals=n)


@pytest.mark.parametrize("style", sorted(set(STYLES) - {"segment_boundaries"}))
def test_every_style_draws_on_the_same_pixel_grid_within_range(fragment, style):
    out = render(fragment, style)
    assert out.rgb.shape == (72, 72, 3) and out.alpha.shape == (72, 72)
    assert np.isfinite(out.rgb).all() and out.rgb.min() >= 0 and out.rgb.max() <= 1
    # the background stays white far from the fragment
    assert np.allclose(out.rgb[0, 0], 1.0, atol=0.05)


@pytest.mark.parametrize("path", sorted(RECIPE_DIR.glob("*.toml")), ids=lambda p: p.stem)
def test_shipped_recipes_load_and_render(fragment, path):
    recipe = load_recipe(path)
    out = render(fragment, recipe)
    assert out.rgb.shape == (72, 72, 3)
    assert parse_recipe(recipe_to_toml(recipe)).layers == recipe.layers


def test_per_segment_layers_draw_only_on_their_segments():
    # two halves that differ in normal: segment 0 and 1; paint one red and one blue
    n = tilted_plane(40, 0)
    n[:, 24:] = tilted_plane(40, 45, 0)[:, 24:]
    img = RGBNImage(albedo=np.full((40, 40, 3), 0.5), mask=np.ones((40, 40), bool), dpi=300, normals=n)
    text = """
    name = "two"
    [segmentation]
    scale = 20.0
    sigma_px = 0.0
    min_size = 50
    [[layer]]
    style = "gooch"
    blue = 1.0
    yellow = 0.0
    alpha = 0.0
    beta = 0.0
    exposure = "none"
    segments = [0]
    [[layer]]
    style = "gooch"
    blue = 0.0
    yellow = 1.0
    alpha = 0.0
    beta = 0.0
    exposure = "none"
    exclude_segments = [0]
    """
    out = render(img, parse_recipe(text)).rgb
    # the larger (left, 24 columns) half is segment 0: its colour has blue only
    assert out[:, :22, 0].max() < 1e-6 and out[:, :22, 2].min() > 0
    assert out[:, 26:, 2].max() < 1e-6 and out[:, 26:, 0].min() > 0


def test_blend_modes_and_opacity_compose_as_documented():
    img = RGBNImage(albedo=np.full((4, 4, 3), 0.5), mask=np.ones((4, 4), bool), dpi=300, normals=tilted_plane(4, 0))
    text = """
    name = "b"
    background = [0.0, 0.0, 0.0]
    [[layer]]
    style = "lambertian"
    light = [0.0, 90.0]
    ambient = 0.0
    colour = false
    exposure = "none"
    [[layer]]
    style = "lambertian"
    light = [0.0, 30.0]
    ambient = 0.0
    colour = false
    exposure = "none"
    blend = "multiply"
    opacity = 0.5
    """
    out = render(img, parse_recipe(text)).rgb
    # base 1.0 (light overhead), multiplied by 0.5 (n.l at 30 deg) at half opacity: 1 + (0.5 - 1) * 0.5
    assert np.allclose(out, 0.75, atol=1e-6)


def test_colour_only_image_skips_normal_styles_instead_of_failing():
    img = RGBNImage(albedo=np.full((8, 8, 3), 0.5), mask=np.ones((8, 8), bool), dpi=300)
    out = render(img, "relief")
    assert out.skipped == ["exaggerated", "ridges_valleys"]
    assert np.allclose(out.rgb, out.rgb[0, 0])


@pytest.mark.parametrize("text,match", [
    ("name='x'\n[[layer]]\nstyle='nope'", "unknown style 'nope'"),
    ("name='x'\n[[layer]]\nstyle='toon'\nlvls=3", r"no parameter\(s\) \['lvls'\]"),
    ("name='x'\n[[layer]]\nstyle='toon'\nblend='hard_light'", "blend"),
    ("name='x'\n[[layer]]\nstyle='toon'\nsegments=[0]", r"\[segmentation\]"),
    ("name='x'\nbits=12\n[[layer]]\nstyle='toon'", "bits"),
    ("name='x'", "at least one"),
    ("name='x'\ncolour='red'\n[[layer]]\nstyle='toon'", "unknown top-level"),
    ("name = [", "not valid TOML"),
])
def test_bad_recipes_are_refused_with_the_bad_entry_named(text, match):
    with pytest.raises(ValueError, match=match):
        parse_recipe(text)


def test_unknown_recipe_name_lists_the_shipped_ones():
    with pytest.raises(FileNotFoundError, match="relief"):
        load_recipe("no-such-recipe")
    with pytest.raises(ValueError, match="unknown style"):
        style_recipe("no-such-style")


@pytest.mark.parametrize("layer, message", [
    ("style='raking'\nelevation_deg='low'", r"'elevation_deg' must be a number"),
    ("style='lambertian'\ncolour=1", r"'colour' must be true or false"),
    ("style='ridges_valleys'\nridge_colour=[1, 0]", r"'ridge_colour' must be an RGB colour"),
    ("style='ridges_valleys'\nvalley_colour=[0, 0, 2]", r"'valley_colour' must be an RGB colour"),
    ("style='toon'\nlevels=2.5", r"'levels' must be a whole number"),
    ("style='exaggerated'\nsigma0_px='fine'", r"'sigma0_px' must be \"auto\" or a number"),
    # "none" is a value of the exposures only: elsewhere it used to fail later, unnamed
    ("style='raking'\nsigma_px='none'", r"'sigma_px' must be \"auto\" or a number"),
    ("style='exaggerated'\ntones='none'", r"'tones' must be \"auto\" or a number"),
    ("style='raking'\nlevel='yes'", r"'level' must be \"auto\", true, false or a number"),
    ("style='lambertian'\nexposure='off'", r"'exposure' must be \"auto\", \"none\" or a \[low, high\] pair"),
])
def test_a_parameter_of_the_wrong_type_is_refused_by_name(layer, message):
    with pytest.raises(ValueError, match=message):
        parse_recipe(f"name='x'\n[[layer]]\n{layer}")


@pytest.mark.parametrize("style", ["raking", "lambertian", "suggestive_contours"])
@pytest.mark.parametrize("level", [True, False])
def test_level_takes_true_and_false_as_documented(style, level):
    # docs/gallery.md: level is "auto" / true / false / sigma in pixels
    recipe = parse_recipe(f"name='x'\n[[layer]]\nstyle='{style}'\nlevel={str(level).lower()}")
    yy, xx = np.mgrid[:48, :48]
    n = np.dstack([0.1 * np.sin(xx / 4.0), 0.1 * np.cos(yy / 5.0), np.ones((48, 48))]).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    image = RGBNImage(np.full((48, 48, 3), 0.4, np.float32), np.ones((48, 48), bool), normals=n, dpi=300.0)
    drawn = render(image, recipe)
    assert (drawn.resolved[-1]["level"] > 0) == level


@pytest.mark.parametrize("style, params", [
    ("lambertian", {}), ("lambertian", {"colour": False}), ("raking", {"colour": True}),
    ("specular", {}), ("normal_unsharp", {}), ("normal_unsharp", {"colour": False}),
    ("gooch", {}), ("albedo", {}), ("colour_relief", {}), ("exaggerated", {"colour": True}),
])
def test_exposure_none_draws_as_computed_for_every_style_that_takes_it(style, params):
    # docs/gallery.md: exposure "none" (as computed) for each style listed with an exposure
    assert "exposure" in STYLES[style].parameters()
    yy, xx = np.mgrid[:48, :48]
    n = np.dstack([0.2 * np.sin(xx / 4.0), np.zeros((48, 48)), np.ones((48, 48))]).astype(np.float32)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    image = RGBNImage(np.full((48, 48, 3), 0.3, np.float32), np.ones((48, 48), bool), normals=n, dpi=300.0)
    drawn = render(image, style_recipe(style, exposure="none", **params))
    assert drawn.resolved[-1]["exposure"] == "none"
    assert np.all(np.isfinite(drawn.rgb)) and drawn.rgb.min() >= 0.0 and drawn.rgb.max() <= 1.0


@pytest.fixture(scope="module")
def painting():
    """A dark, low-contrast 'painting': two dull pigments, fine brush-stroke relief, 8-bit-like noise."""
    rng = np.random.default_rng(5)
    import cv2

    size = 160
    strokes = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), sigmaX=6, sigmaY=1.2) * 6
    gy, gx = np.gradient(strokes)
    n = np.stack([-gx, gy, np.ones_like(gx)], axis=-1)
    n[..., :2] += rng.normal(0, 0.008, (size, size, 2))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    # dark umber shading into a dull ochre, and a red passage: a picture whose median is dark
    t = np.linspace(0, 1, size, dtype=np.float32)[None, :, None]
    albedo = (0.02 + 0.12 * t) * np.array([1.0, 0.8, 0.5], np.float32) + np.zeros((size, 1, 1), np.float32)
    albedo[size // 3:size // 2, :] = (0.09, 0.03, 0.02)
    return RGBNImage(albedo=albedo, mask=np.ones((size, size), bool), dpi=300.0, normals=n.astype(np.float32))


def _tone_span(rgb):
    lum = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    p5, p95 = np.percentile(lum, [5, 95])
    q = np.round(rgb * 255)
    return p95 - p5, float(np.mean((q.max(axis=2) >= 255) | (q.min(axis=2) <= 0)))  # a channel at 0 or 255


SHADING = ["albedo", "colour_relief", "normal_unsharp", "specular", "lambertian", "raking", "toon", "gooch",
           "exaggerated", "mean_curvature", "multiscale_mean_curvature", "watercolour"]


@pytest.mark.parametrize("style", SHADING)
def test_every_default_uses_half_the_tone_range_and_saturates_little_on_a_dark_painting(painting, style):
    span, clipped = _tone_span(render(painting, style).rgb)
    assert span >= 0.5, f"{style}: 5-95 % span {span:.2f}"
    assert clipped <= 0.02, f"{style}: {100 * clipped:.1f} % saturated"


def test_colour_relief_keeps_the_paint_colour_and_shows_the_strokes(painting):
    import cv2

    out = render(painting, "colour_relief").rgb
    flat = render(painting, "albedo").rgb
    lab_out = cv2.cvtColor(out, cv2.COLOR_RGB2Lab)
    lab_flat = cv2.cvtColor(flat, cv2.COLOR_RGB2Lab)
    # hue of each half kept (median over the half), lightness varies with the strokes
    for half in (np.s_[:50, :], np.s_[55:78, :]):
        h_out = np.degrees(np.arctan2(np.median(lab_out[half][..., 2]), np.median(lab_out[half][..., 1])))
        h_flat = np.degrees(np.arctan2(np.median(lab_flat[half][..., 2]), np.median(lab_flat[half][..., 1])))
        assert abs(h_out - h_flat) < 5.0
    assert (lab_out[..., 0] - lab_flat[..., 0]).std() > 2.0  # strokes change the lightness
    # the default recipe is colour plus relief: the same colours, not halved by a multiply
    default = render(painting, "default").rgb
    assert np.median(default) == pytest.approx(np.median(flat), abs=0.05)


def test_resolved_values_redraw_the_same_picture(painting):
    first = render(painting, "raking")
    again = render(painting, "raking", resolved=first.resolved)
    assert np.array_equal(first.rgb, again.rgb)
    assert set(first.resolved[0]) >= {"sigma_px", "level", "exposure"}


def test_every_style_parameter_is_documented_with_its_meaning():
    from common.render.recipes import PARAM_DOCS

    missing = {(s.name, k) for s in STYLES.values() for k in s.parameters() if not PARAM_DOCS.get(k)}
    assert not missing


def test_segment_boundaries_as_a_style_brings_its_own_segmentation(fragment):
    recipe = style_recipe("segment_boundaries")
    assert recipe.segmentation is not None
    out = render(fragment, recipe)
    assert out.rgb.shape == (72, 72, 3) and np.isfinite(out.rgb).all()


def test_layers_sharing_smoothed_normals_draw_what_each_draws_alone(fragment):
    """In a recipe the layers share the normals smoothed at one scale (exaggerated's finest level,
    discontinuity lines at the noise scale): the picture is the layers drawn one by one, each
    smoothing for itself, composed; and the smoothing runs once."""
    import common.rgbn.smoothing as smoothing
    from common.render import recipes

    text = """
name = "shared"
[[layer]]
style = "exaggerated"
[[layer]]
style = "discontinuity_lines"
"""
    from common.render import shading

    sigmas = []
    real = smoothing.iter_scale_space

    def counted(normals, sigmas_px, **k):
        sigmas_px = list(sigmas_px)
        sigmas.extend(sigmas_px)
        return real(normals, sigmas_px, **k)

    smoothing.iter_scale_space = shading.iter_scale_space = counted
    try:
        both = render(fragment, parse_recipe(text))
    finally:
        smoothing.iter_scale_space = shading.iter_scale_space = real
    s0 = both.resolved[0]["sigma0_px"]
    assert s0 == both.resolved[1]["sigma_px"] > 0          # one scale for both layers
    assert sigmas.count(s0) == 1                            # smoothed at it once, not once per layer
    canvas = np.ones((72, 72, 3), np.float32)
    for style in ("exaggerated", "discontinuity_lines"):
        layer = STYLES[style].draw(fragment)                                 # alone: nothing shared
        canvas = recipes._blend(canvas, layer.rgb, layer.alpha.astype(np.float32), "normal")
    assert np.abs(both.rgb - np.clip(canvas, 0, 1)).max() < 1e-6


def test_the_half_vector_cosine_under_a_levelled_light_is_that_of_each_pixels_half_vector(fragment):
    """Independent reference: the smoothed normals dotted with half_vector of the per-pixel light
    (level_light of the coarse field), against _cosines' n . h taken from n . l and n . v."""
    from common.render import enhance, recipes
    from common.rgbn.smoothing import smooth_normals

    image = RGBNImage(albedo=fragment.albedo, mask=fragment.mask, dpi=fragment.dpi,
                      normals=tilted_plane(72, 20.0, 30.0) * 0.5 + fragment.normals * 0.5)
    image.normals /= np.linalg.norm(image.normals, axis=2, keepdims=True)
    recipes._cache.clear()
    try:
        r = {}
        cos_nl, cos_nh = recipes._cosines(image, 1.5, (135.0, 20.0), True, r, half=True)
        field = enhance.level_light((135.0, 20.0), recipes._coarse(image, r["level"]), image.shape)
    finally:
        recipes._cache.clear()
    n = smooth_normals(image.normals, 1.5, mask=image.mask)
    assert np.ptp(field[..., 2]) > 0.01                     # a light that varies over the image
    assert np.abs(cos_nl - np.einsum("...i,...i->...", n, field)).max() < 2e-6
    assert np.abs(cos_nh - np.einsum("...i,...i->...", n, enhance.half_vector(field))).max() < 2e-6


@pytest.fixture(scope="module")
def segmented():
    """A 384 x 288 relief with hand-made segments: segment 0 the most of it, and small ones in the
    middle, on the left and bottom edges and in a corner, for per-segment layers to draw."""
    import cv2

    from tests.rgbn.analytic import normals_from_height

    h, w = 384, 288
    rng = np.random.default_rng(3)
    height = cv2.GaussianBlur(rng.standard_normal((h, w)).astype(np.float32), (0, 0), 5) * 60
    gy, gx = np.gradient(height)
    normals = normals_from_height(gx * 0.5, -gy * 0.5).astype(np.float32)
    albedo = np.full((h, w, 3), 0.55, np.float32)
    albedo[:, 130:] = (0.6, 0.3, 0.2)
    albedo += rng.normal(0.0, 0.03, albedo.shape).astype(np.float32)
    mask = np.ones((h, w), bool)
    mask[:12, 220:] = False                       # a notch in the outline
    labels = np.zeros((h, w), np.int32)
    labels[200:230, 120:160] = 1                  # inside
    labels[20:70, :14] = 2                        # on the left edge
    labels[370:, 30:90] = 3                       # on the bottom edge
    labels[330:, 250:] = 4                        # in the bottom-right corner
    labels[~mask] = -1
    return RGBNImage(albedo=np.clip(albedo, 0.0, 1.0), mask=mask, dpi=300.0, normals=normals), labels


def _per_segment(style, lines=False, **params):
    """A recipe: lambertian shading, ``style`` on every segment but 0, and with ``lines``
    discontinuity lines on segments 1 and 2 (an ink layer, drawn whole and masked)."""
    from common.render.recipes import Recipe

    return Recipe(name="per-segment", segmentation={"scale": 100.0},
                  layers=[{"style": "lambertian"}, dict(style=style, exclude_segments=[0], **params)]
                  + ([{"style": "discontinuity_lines", "segments": [1, 2]}] if lines else []))


@pytest.mark.parametrize("style", ["toon", "albedo", "normals"])
def test_a_per_segment_layer_drawn_on_windows_is_the_layer_drawn_whole_then_masked(segmented, style, monkeypatch):
    """A per-segment layer whose "auto" values come from the image's inputs is drawn only over
    windows around its segments (each with the style's reach as a margin), with the values a
    drawing of the whole image picks (palette, exposure, smoothing, levelling): the picture is the
    one drawn whole and then masked, to 1e-3/255 (the blur at a window's border is not read)."""
    from common.render import recipes

    image, labels = segmented
    recipe = _per_segment(style, lines=True)
    sizes = []
    draw = recipes.STYLES[style].draw

    @functools.wraps(draw)
    def counted(im, **kw):
        sizes.append(im.shape)
        return draw(im, **kw)

    monkeypatch.setitem(recipes.STYLES, style, recipes.Style(style, counted, recipes.STYLES[style].needs, ""))
    windowed = recipes._render_whole(image, recipe, None, None, labels)
    assert len(sizes) > 2 and all(s[0] * s[1] < 0.3 * labels.size for s in sizes)   # windows, not the image
    monkeypatch.setattr(recipes, "WINDOW_SHARE", -1.0)                            # the whole image, masked
    whole = recipes._render_whole(image, recipe, None, None, labels)
    assert sizes[-1] == image.shape
    assert windowed.resolved == whole.resolved
    assert np.abs(windowed.rgb - whole.rgb).max() <= 1e-3 / 255
    assert np.abs(windowed.alpha - whole.alpha).max() == 0.0


@pytest.mark.parametrize("style", sorted(["toon", "lambertian", "raking", "gooch", "exaggerated", "specular",
                                          "mean_curvature", "multiscale_mean_curvature", "colour_relief",
                                          "normal_unsharp"]))
def test_every_windowed_style_given_its_values_draws_on_windows_what_it_draws_whole(segmented, style, monkeypatch):
    """Given its values (as a tile is given the calibration's), each style drawn on windows around
    its segments is the style drawn on the whole image and masked, within the 1/255 tiles allow
    (a coarse grid of a window can differ from the image's)."""
    from common.render import recipes

    assert style in recipes._WINDOWED
    image, labels = segmented
    params = {"scales": 3} if style == "exaggerated" else {}
    first = recipes._render_whole(image, _per_segment(style, **params), None, None, labels)
    resolved = first.resolved
    monkeypatch.setattr(recipes, "WINDOW_SHARE", -1.0)
    whole = recipes._render_whole(image, _per_segment(style, **params), None, resolved, labels)
    monkeypatch.setattr(recipes, "WINDOW_SHARE", 1.0)
    windowed = recipes._render_whole(image, _per_segment(style, **params), None, resolved, labels)
    assert windowed.resolved == whole.resolved == resolved
    assert np.abs(windowed.rgb - whole.rgb).max() <= 1.0 / 255
    assert np.ptp(whole.rgb[labels > 0]) > 0.1   # something drawn there


def test_a_per_segment_layer_in_tiles_is_drawn_on_each_tiles_core_only(segmented, monkeypatch):
    """In tiles the per-segment layers are drawn for the tile's core only (the halo is thrown
    away), and the tiles still draw the whole image's picture (to 8-bit rounding)."""
    import common.rgbn.segmentation as seg
    from common.render import recipes
    from common.render.tiles import render_tiled

    image, labels = segmented
    recipe = _per_segment("toon")
    whole = recipes._render_whole(image, recipe, None, None, labels)
    monkeypatch.setattr(seg, "segment_source", lambda source, **kw: labels)
    tiled = render_tiled(image, recipe, tile=64)
    assert tiled.resolved == whole.resolved
    assert np.abs(np.round(whole.rgb * 255) - tiled.rgb.astype(np.float64)).max() <= 1.0


def test_shown_windows_hold_every_shown_pixel_with_its_margin():
    from common.render.tiles import shown_windows

    rng = np.random.default_rng(0)
    shown = np.zeros((300, 500), bool)
    shown[rng.integers(0, 300, 40), rng.integers(0, 500, 40)] = True
    shown[:5, :5] = shown[-3:, 200:260] = shown[100:103, -2:] = True
    for margin in (0, 7, 40):
        windows = shown_windows(shown, margin, block=16, band=64)
        covered = np.zeros(shown.shape, bool)
        for (r0, r1, c0, c1), (a, b, c, d) in windows:
            covered[r0:r1, c0:c1] = True
            assert (a, b, c, d) == (max(0, r0 - margin), min(300, r1 + margin), max(0, c0 - margin),
                                    min(500, c1 + margin))
        assert covered[shown].all()
        if margin < 40:
            assert covered.sum() < 0.5 * shown.size   # cores around the pixels, not the image
    assert shown_windows(np.zeros((10, 10), bool), 3) == []


def test_a_normal_blend_of_partial_ink_is_base_plus_its_difference_times_alpha():
    from common.render.recipes import _blend

    rng = np.random.default_rng(1)
    base = rng.random((50, 40, 3), dtype=np.float32)
    rgb = rng.random((50, 40, 3), dtype=np.float32)
    alpha = rng.random((50, 40), dtype=np.float32)
    alpha[:10] = 0.0
    alpha[30:] = 0.0
    expected = base + (rgb - base) * alpha[..., None]
    assert np.array_equal(_blend(base.copy(), rgb, alpha, "normal"), expected)


def test_auto_sigma_px_is_the_noise_scale_times_the_factor_the_docs_state():
    from common.render.recipes import PARAM_DOCS

    rng = np.random.default_rng(3)
    n = np.dstack([rng.normal(0, 0.045, (64, 64)), rng.normal(0, 0.045, (64, 64)), np.ones((64, 64))])
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    image = RGBNImage(np.full((64, 64, 3), 0.4, np.float32), np.ones((64, 64), bool), normals=n, dpi=300.0)
    base = render(image, style_recipe("lambertian")).resolved[-1]["sigma_px"]
    assert base > 2.0   # above every floor
    factors = {name: render(image, style_recipe(name)).resolved[-1]["sigma_px"] / base
               for name, s in STYLES.items() if s.parameters().get("sigma_px") == "auto"}
    # discontinuity lines smooth at the noise scale itself (exaggerated shading's finest level)
    assert {k for k, f in factors.items() if abs(f - 1) < 0.01} == {"specular", "lambertian", "raking",
                                                                   "discontinuity_lines"}
    doubled = sorted(k for k, f in factors.items() if abs(f - 2) < 0.01)
    assert doubled == ["gooch", "ridges_valleys", "suggestive_contours", "suggestive_contours_object"]
    assert [k for k, f in factors.items() if abs(f - 3) < 0.01] == ["toon"]
    doc = PARAM_DOCS["sigma_px"]
    assert all(k in doc.split("x2 for ")[1].split("x3 for")[0] for k in doubled)
    assert "x3 for toon" in doc and "lines" not in doc


@pytest.mark.parametrize("tile", [None, 16])
def test_a_colour_only_drawing_warns_once_unless_its_caller_reports_it(caplog, tile):
    """render() says once which styles a colour-only image cannot have (``tessera render`` relies on it), also
    when it draws in tiles (each tile warned before); a caller that reports them itself (the renderer service,
    naming the face) asks for none and finds them in ``skipped``."""
    img = RGBNImage(albedo=np.full((40, 40, 3), 0.5), mask=np.ones((40, 40), bool), dpi=300)
    with caplog.at_level("WARNING", logger="common.render"):
        out = render(img, "relief", tile=tile)
    assert [r.getMessage() for r in caplog.records if "no normals" in r.getMessage()] == [
        "image has no normals: skipped exaggerated, ridges_valleys"]
    caplog.clear()
    with caplog.at_level("WARNING", logger="common.render"):
        quiet = render(img, "relief", tile=tile, warn_skipped=False)
    assert quiet.skipped == out.skipped == ["exaggerated", "ridges_valleys"] and "no normals" not in caplog.text


@pytest.mark.parametrize("tile", [None, 16])
def test_a_colour_only_face_keeps_its_colour_under_the_lines_left(tile):
    """The default recipe on a colour-only face (an imported picture) skipped colour_relief and drew only the
    outline lines on the recipe's white background: a white silhouette in every export and download. With no
    colour layer left, the albedo is drawn as captured under the lines that remain (not exposed: the automatic
    stretch turned a pale plaster's pink band near black)."""
    from common.render._util import display_albedo

    albedo = np.full((40, 40, 3), 0.6, np.float32)
    albedo[:, 20:] = (0.5, 0.25, 0.15)   # two paints that the drawing must show
    mask = np.zeros((40, 40), bool)
    mask[4:36, 4:36] = True
    img = RGBNImage(albedo=albedo, mask=mask, dpi=300)
    out = render(img, "default", tile=tile, warn_skipped=False)
    assert out.skipped == ["colour_relief"]
    rgb = out.rgb / 255.0 if out.rgb.dtype == np.uint8 else out.rgb   # the tiled drawing keeps 8 bits
    left, right = rgb[20, 10], rgb[20, 28]
    assert np.abs(left - right).max() > 0.1          # the paints differ, not one flat white
    assert right[0] > right[1] > right[2]             # the red-brown paint stays red-brown
    # inside the outline: the albedo as captured, through the display transform alone
    assert np.allclose(rgb[10:30, 10:30], display_albedo(albedo)[10:30, 10:30], atol=0.02)
