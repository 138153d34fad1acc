import cv2
import h5py
import numpy as np
import pytest

from common.render.recipes import STYLES, load_recipe, render, style_recipe
from common.render.tiles import H5Source, MemorySource, halo_px, render_tiled
from common.rgbn.image import RGBNImage, write_rgbn
from common.rgbn.segmentation import segment_rgbn
from tests.rgbn.analytic import normals_from_height

SIZE, TILE = 256, 64


@pytest.fixture(scope="module")
def relief():
    """A noisy multi-scale relief with two colours and a round outline."""
    rng = np.random.default_rng(0)
    blur = lambda a, s: cv2.GaussianBlur(a.astype(np.float32), (0, 0), s)  # noqa: E731
    h = blur(rng.standard_normal((SIZE, SIZE)), 6) * 40 + blur(rng.standard_normal((SIZE, SIZE)), 1.5) * 2
    gy, gx = np.gradient(h)
    n = normals_from_height(gx * 0.5, -gy * 0.5)
    n[..., :2] += rng.normal(0, 0.01, (SIZE, SIZE, 2))
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE]
    mask = (xx - SIZE / 2) ** 2 + (yy - SIZE / 2) ** 2 < (0.47 * SIZE) ** 2
    albedo = np.zeros((SIZE, SIZE, 3), np.float32)
    albedo[:] = (0.5, 0.3, 0.2)
    albedo[:, SIZE // 2:] = (0.2, 0.3, 0.5)
    return RGBNImage(albedo=albedo, mask=mask, dpi=300.0, normals=n.astype(np.float32))


CASES = [s for s in STYLES if s not in ("segment_boundaries", "exaggerated")] + ["exaggerated", "default", "toon"]


@pytest.mark.parametrize("name", CASES)
def test_tiles_with_overlap_draw_the_same_picture_as_the_whole_image(relief, name):
    if name in ("default", "toon"):
        recipe = load_recipe(name)
    else:
        recipe = style_recipe(name, **({"scales": 3} if name == "exaggerated" else {}))
    whole = render(relief, recipe)
    tiled = render_tiled(relief, recipe, tile=TILE)
    # the tiles really are tiles: a core plus its halo is smaller than the image
    assert TILE + halo_px(recipe, relief.dpi, whole.resolved) < SIZE
    assert tiled.rgb.dtype == np.uint8 and tiled.rgb.shape == (SIZE, SIZE, 3)
    diff = np.abs(np.round(whole.rgb * 255) - tiled.rgb.astype(np.float64))
    # no seams: equal up to the 8-bit rounding of the drawing
    assert diff.max() <= 1.0
    assert whole.resolved == tiled.resolved  # one exposure for all tiles: the whole image's


def test_an_image_read_window_by_window_from_hdf5_draws_the_same(relief, tmp_path):
    with h5py.File(tmp_path / "f.h5", "w") as f:
        write_rgbn(f, relief)
    with h5py.File(tmp_path / "f.h5", "r") as f:
        source = H5Source(f)
        assert source.shape == relief.shape
        a = render_tiled(source, "raking", tile=TILE)
    b = render_tiled(MemorySource(relief), "raking", tile=TILE)
    assert np.array_equal(a.rgb, b.rgb)


def test_render_goes_to_tiles_for_a_large_image_and_returns_8_bit(relief):
    out = render(relief, "colour_relief", tile=TILE)
    assert out.rgb.dtype == np.uint8
    whole = render(relief, "colour_relief")
    assert np.abs(np.round(whole.rgb * 255) - out.rgb).max() <= 1


def test_a_recipe_with_segments_draws_the_same_in_tiles_as_whole(relief):
    """The segments are found once for the whole image and every tile draws with its window of
    them: no seams, the same picture as the whole drawing (up to 8-bit rounding)."""
    recipe = load_recipe("segments")
    recipe.layers[0]["scales"] = 3  # exaggerated: a halo that fits this small image, as above
    whole = render(relief, recipe)
    tiled = render(relief, recipe, tile=TILE)
    assert len(np.unique(segment_rgbn(relief.albedo, relief.normals, mask=relief.mask,
                                      **recipe.segmentation))) > 2  # segments to draw
    assert tiled.rgb.dtype == np.uint8 and whole.rgb.dtype == np.float32
    assert TILE + halo_px(recipe, relief.dpi, whole.resolved) < SIZE
    assert np.abs(np.round(whole.rgb * 255) - tiled.rgb.astype(np.float64)).max() <= 1.0
    assert whole.resolved == tiled.resolved


def test_exaggerated_with_all_six_scales_draws_the_same_in_tiles_with_its_3_sigma_halo():
    """Exaggerated shading's halo reaches 3 sigma of its base level (not 4): with the default six
    scales and contrast, on a relief whose slopes reach the tile borders, the tiles still agree
    with the whole drawing up to 8-bit rounding."""
    size = 448
    rng = np.random.default_rng(1)
    blur = lambda a, s: cv2.GaussianBlur(a.astype(np.float32), (0, 0), s)  # noqa: E731
    h = blur(rng.standard_normal((size, size)), 24) * 400 + blur(rng.standard_normal((size, size)), 3) * 6
    gy, gx = np.gradient(h)
    n = normals_from_height(gx * 0.5, -gy * 0.5)
    image = RGBNImage(albedo=np.full((size, size, 3), 0.5, np.float32), mask=np.ones((size, size), bool),
                      dpi=300.0, normals=n.astype(np.float32))
    recipe = style_recipe("exaggerated", sigma0_px=1.0)
    whole = render(image, recipe)
    halo = halo_px(recipe, image.dpi, whole.resolved)
    assert halo == int(np.ceil(3 * 64 + 4))                       # sigma0 2^6 = 64 px, 3 sigma
    tiled = render_tiled(image, recipe, tile=128)
    diff = np.abs(np.round(whole.rgb * 255) - tiled.rgb.astype(np.float64))
    assert diff.max() <= 1.0
    assert np.ptp(whole.rgb) > 0.5                                # a picture with relief in it


def test_tiles_take_the_levelling_field_from_the_whole_image_and_need_no_halo_for_it(relief):
    """Levelling's coarse normal field (4 sigma = 160 px of reach here) is computed once for the
    whole image and every tile interpolates its window of it: the halo does not grow with it and
    the tiles still draw the whole image's picture."""
    recipe = style_recipe("raking", level=40.0)
    whole = render(relief, recipe)
    assert halo_px(recipe, relief.dpi, whole.resolved) >= 4 * 40
    assert halo_px(recipe, relief.dpi, whole.resolved, whole_levels={40.0}) < 40
    tiled = render_tiled(relief, recipe, tile=TILE)
    assert np.abs(np.round(whole.rgb * 255) - tiled.rgb.astype(np.float64)).max() <= 1.0
    assert np.abs(np.round(render(relief, style_recipe("suggestive_contours", level=40.0)).rgb * 255)
                  - render_tiled(relief, style_recipe("suggestive_contours", level=40.0), tile=TILE).rgb).max() <= 1.0
