import numpy as np
import pytest

from common.render.shadows import discontinuity_shadows, discontinuity_sources
from tests.rgbn.analytic import tilted_plane


def wall(size=40):
    """A vertical step: the occluding (higher) side is to the left of column 20."""
    d = np.zeros((size, size, 2), np.float32)
    d[:, 20] = (-1.0, 0.0)
    return d


def test_shadow_falls_away_from_the_light_and_fades_over_its_length():
    s = discontinuity_shadows(wall(), (180.0, 30.0), length_px=8, softness_px=0)  # light from the left
    row = s[20]
    assert row[20] == pytest.approx(1.0)
    for t in range(1, 8):
        assert row[20 + t] == pytest.approx(1 - t / 8, abs=1e-6)  # eq. 7.10
    assert row[28:].max() == 0 and row[:20].max() == 0


def test_a_discontinuity_facing_away_from_the_light_casts_no_shadow():
    assert discontinuity_shadows(wall(), (0.0, 30.0), softness_px=0).max() == 0  # eq. 7.9
    assert discontinuity_shadows(wall(), (0.0, 90.0), softness_px=0).max() == 0  # light from above


def test_oblique_light_casts_a_diagonal_shadow():
    d = np.zeros((40, 40, 2), np.float32)
    d[20, 20] = (-np.sqrt(0.5), np.sqrt(0.5))  # occluder up-left
    s = discontinuity_shadows(d, (135.0, 45.0), length_px=6, softness_px=0)
    # the shadow runs down-right (rows increase, columns increase)
    assert s[22, 22] > 0.4 and s[24, 24] > 0 and s[17, 17] == 0


def test_outline_sources_point_into_the_fragment_so_it_casts_a_drop_shadow():
    mask = np.zeros((40, 40), bool)
    mask[10:30, 10:30] = True
    d = discontinuity_sources(tilted_plane(40, 0), mask=mask)
    assert d[20, 10, 0] > 0.5  # left edge: the fragment (occluder) is to the right
    s = discontinuity_shadows(d, (135.0, 45.0), length_px=5, softness_px=0)
    assert s[32, 25] > 0.2 and s[8, 15] == 0  # below-right of the fragment, not above-left


def test_steep_walls_from_normals_point_up_slope():
    n = tilted_plane(8, 80, 0)  # facing right: the wall's top is to the left
    d = discontinuity_sources(n, outline=False)
    assert (d[..., 0] < -0.9).all()


def test_bad_discontinuity_shape_is_refused():
    with pytest.raises(ValueError, match="discontinuity"):
        discontinuity_shadows(np.zeros((4, 4, 3)))
