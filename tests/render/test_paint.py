import numpy as np

from common.render.paint import paper_texture, pigment_density, watercolour
from tests.rgbn.analytic import gaussian_bump


def test_density_one_keeps_the_colour_and_higher_density_darkens():
    c = np.array([[[0.2, 0.5, 0.9]]], np.float32)
    assert np.allclose(pigment_density(c, np.ones((1, 1))), c)
    darker = pigment_density(c, np.full((1, 1), 1.5))
    # Bousseau et al. 2006: C' = C - (C - C^2)(d - 1)
    assert np.allclose(darker, c - (c - c * c) * 0.5)
    assert (darker <= c).all()


def test_watercolour_is_deterministic_and_darker_on_shadowed_slopes():
    n = gaussian_bump(64, 0.1, 1.0, 1.0)
    colour = np.full((64, 64, 3), 0.7, np.float32)
    a = watercolour(colour, n, (0.0, 45.0), paper=0.0, edge_darkening=0.0)
    b = watercolour(colour, n, (0.0, 45.0), paper=0.0, edge_darkening=0.0)
    assert np.array_equal(a, b)
    # light from +x: the x > 0 flank (column 40) is lit, the x < 0 flank (column 24) gets more pigment
    assert a[32, 24].mean() < a[32, 40].mean() - 0.05


def test_paper_texture_is_seeded_and_zero_mean():
    t1, t2 = paper_texture((64, 64), seed=5), paper_texture((64, 64), seed=5)
    assert np.array_equal(t1, t2) and abs(float(t1.mean())) < 0.2
