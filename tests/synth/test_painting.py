import numpy as np
import pytest

from common.synth.painting import paint_wall, painting_from_image


def test_painting_is_reproducible_and_in_range():
    a = paint_wall(300, 200, np.random.default_rng(5), res_mm=0.5)
    b = paint_wall(300, 200, np.random.default_rng(5), res_mm=0.5)
    assert a.albedo.shape == (400, 600, 3)
    assert np.array_equal(a.albedo, b.albedo)
    assert a.albedo.min() >= 0 and a.albedo.max() <= 1


def test_horizontal_strings_lie_on_colour_boundaries():
    p = paint_wall(300, 260, np.random.default_rng(6), res_mm=0.5)
    horizontal = [s for s in p.string_lines if s[0][1] == s[1][1] and s[0][0] == 0.0]
    assert horizontal, "the registers are laid out with strings"
    jumps = []
    for (_, y), _ in horizontal:
        above = p.sample(np.array([150.0]), np.array([y - 1.5]))
        below = p.sample(np.array([150.0]), np.array([y + 1.5]))
        jumps.append(np.abs(above - below).max())
    # most strings separate two colours (the fields differ by far more than the mottling)
    assert np.median(jumps) > 0.05


def test_user_picture_sets_the_wall_size_and_linearises_srgb():
    img = np.zeros((50, 100, 3), np.uint8)
    img[:, :50] = 255
    img[:, 50:] = 188  # sRGB 188 ~ linear 0.5
    p = painting_from_image(img, 200.0, res_mm=1.0)
    assert p.albedo.shape == (100, 200, 3)
    assert p.albedo[50, 20, 0] == pytest.approx(1.0, abs=1e-3)
    assert p.albedo[50, 180, 0] == pytest.approx(0.5, abs=0.01)


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="width_mm"):
        paint_wall(-1, 10, np.random.default_rng(0))
    with pytest.raises(ValueError, match="style"):
        paint_wall(10, 10, np.random.default_rng(0), style="baroque")


@pytest.mark.parametrize("style", ["aegean", "roman"])
def test_any_wall_size_and_seed_paints(style):
    for seed in range(25):
        rng = np.random.default_rng(seed)
        w, h = rng.uniform(20, 600), rng.uniform(20, 400)
        p = paint_wall(w, h, rng, res_mm=4.0, style=style)
        assert np.isfinite(p.albedo).all()
