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
