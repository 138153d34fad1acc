"""Colour descriptors (common/features/colour.py)."""

import numpy as np
import pytest

from common.features.colour import colour_statistics


def test_uniform_colour_has_zero_variance_and_its_own_mean_and_saturation():
    s = colour_statistics(np.full((8, 8, 3), [0.8, 0.4, 0.2]), np.ones((8, 8), bool))
    assert (s["colour_mean_r"], s["colour_mean_g"], s["colour_mean_b"]) == pytest.approx((0.8, 0.4, 0.2), rel=1e-6)
    assert s["colour_variance"] == pytest.approx(0.0, abs=1e-12)
    assert s["saturation"] == pytest.approx((0.8 - 0.2) / 0.8, rel=1e-6)


def test_two_colour_halves_have_the_analytic_variance():
    a = np.zeros((10, 10, 3))
    a[:, :5] = (0.2, 0.2, 0.2)
    a[:, 5:] = (0.6, 0.2, 0.4)
    s = colour_statistics(a, np.ones((10, 10), bool))
    # a two-point distribution with weights 1/2 has variance (d/2)^2 per channel
    assert s["colour_variance"] == pytest.approx(0.2 ** 2 + 0 + 0.1 ** 2, rel=1e-5)
    assert s["saturation"] == pytest.approx((0.0 + (0.6 - 0.2) / 0.6) / 2, rel=1e-6)


def test_only_masked_pixels_count_and_grey_is_unsaturated():
    a = np.full((6, 6, 3), 0.5)
    a[0] = (1.0, 0.0, 0.0)  # bright red row outside the mask
    m = np.ones((6, 6), bool)
    m[0] = False
    s = colour_statistics(a, m)
    assert s["colour_mean_r"] == pytest.approx(0.5, rel=1e-6) and s["saturation"] == 0.0


def test_empty_region_gives_nan_and_bad_shapes_are_refused():
    s = colour_statistics(np.zeros((4, 4, 3)), np.zeros((4, 4), bool))
    assert all(np.isnan(v) for v in s.values())
    with pytest.raises(ValueError, match="albedo"):
        colour_statistics(np.zeros((4, 4)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="mask"):
        colour_statistics(np.zeros((4, 4, 3)), np.ones((3, 3), bool))
