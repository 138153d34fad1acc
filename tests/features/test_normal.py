"""Normal-map descriptors: normal-z statistics, eq. 5.3, discontinuity (common/features/normal.py)."""

import numpy as np
import pytest

from common.features.normal import neighbour_differences, normal_discontinuity, normal_statistics


def _tilted(theta_deg, phi_deg, shape=(16, 16)):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    n = np.empty(shape + (3,))
    n[...] = (np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t))
    return n


def test_flat_surface_has_nz_one_no_variance_no_variation():
    n = _tilted(0, 0)
    s = normal_statistics(np.full((16, 16, 3), 0.5), n, np.ones((16, 16), bool))
    assert s["normal_z_mean"] == pytest.approx(1.0)
    assert s["normal_z_variance"] == pytest.approx(0.0, abs=1e-12)
    assert s["colour_normal_svd"] == pytest.approx(0.0, abs=1e-6)


def test_two_facets_give_the_analytic_nz_statistics_and_svd():
    # half the pixels tilted 60 deg: nz is 1 or 0.5, mean 0.75, variance 0.0625
    n = _tilted(0, 0)
    n[:, 8:] = _tilted(60, 30, (16, 8))
    a = np.full((16, 16, 3), 0.5)
    s = normal_statistics(a, n, np.ones((16, 16), bool))
    assert s["normal_z_mean"] == pytest.approx(0.75, rel=1e-5)
    assert s["normal_z_variance"] == pytest.approx(0.0625, rel=1e-4)
    # centred stack has rank one: the singular value / sqrt(n) is half the distance of the facets
    d = np.linalg.norm(n[0, 8] - n[0, 0])
    assert s["colour_normal_svd"] == pytest.approx(d / 2, rel=1e-5)


def test_svd_variation_is_invariant_to_rotating_the_normals_in_the_image_plane():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(20, 20, 3))
    n[..., 2] = np.abs(n[..., 2]) + 2
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    a = rng.uniform(0, 1, (20, 20, 3))
    m = np.ones((20, 20), bool)
    c, s_ = np.cos(1.1), np.sin(1.1)
    r = n.copy()
    r[..., 0], r[..., 1] = c * n[..., 0] - s_ * n[..., 1], s_ * n[..., 0] + c * n[..., 1]
    assert normal_statistics(a, r, m)["colour_normal_svd"] == pytest.approx(
        normal_statistics(a, n, m)["colour_normal_svd"], rel=1e-5)


def test_step_in_nz_is_counted_above_0_46():
    nz = np.ones((20, 20))
    nz[:, 10:] = 0.0  # a step of 1: the central difference is 0.5 on the two columns beside it
    st = normal_discontinuity(nz, np.ones((20, 20), bool))
    assert st["disc_frac_046"] == pytest.approx(2 / 18)  # interior pixels: 18 columns
    assert neighbour_differences(nz, np.ones((20, 20), bool)).max() == pytest.approx(0.5, rel=1e-6)


def test_discontinuity_statistics_of_a_known_distribution():
    # a ramp of nz has a constant gradient: all differences equal, ratio 1, no spread
    yy, xx = np.mgrid[:30, :30]
    st = normal_discontinuity(0.5 + 0.01 * xx, np.ones((30, 30), bool))
    assert st["disc_ratio_80_50"] == pytest.approx(1.0, rel=1e-4)
    assert np.isnan(st["disc_skewness"]) and st["disc_frac_046"] == 0.0


def test_discontinuity_is_the_same_along_rows_and_columns():
    rng = np.random.default_rng(2)
    nz = rng.uniform(0.8, 1.0, (40, 40))
    m = np.ones((40, 40), bool)
    a, b = normal_discontinuity(nz, m), normal_discontinuity(nz.T, m)
    for k in a:
        assert a[k] == pytest.approx(b[k], rel=1e-5)


def test_too_few_pixels_give_nan_and_bad_shapes_are_refused():
    assert all(np.isnan(v) for v in normal_discontinuity(np.ones((3, 3)), np.ones((3, 3), bool)).values())
    with pytest.raises(ValueError, match="mask"):
        normal_discontinuity(np.ones((5, 5)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="normals"):
        normal_statistics(np.zeros((4, 4, 3)), np.zeros((4, 4)), np.ones((4, 4), bool))
