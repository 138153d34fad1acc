"""joint_bilateral(filter_normals=False): the normals steer the colour's smoothing but are not filtered."""

import numpy as np

from common.rgbn.bilateral import joint_bilateral


def _scene(n=96, seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n]
    normals = np.zeros((n, n, 3), np.float32)
    normals[..., 2] = 1
    normals[:, n // 2:] = (0.6, 0.0, 0.8)               # a crease down the middle
    albedo = np.full((n, n, 3), 0.5, np.float32)
    albedo[yy > n // 3] = (0.7, 0.3, 0.2)                # a colour edge across it
    albedo += rng.normal(0, 0.03, albedo.shape).astype(np.float32)
    return np.clip(albedo, 0, 1), normals


def test_colour_only_matches_the_joint_filter_within_a_few_thousandths():
    albedo, normals = _scene()
    ref, ref_n = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=0.08, sigma_n=0.3)
    fast, fast_n = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=0.08, sigma_n=0.3, filter_normals=False)
    assert fast_n is None and ref_n is not None
    assert np.abs(fast - ref).max() < 2e-3
    # the exact 2-D window has no second guide: identical
    ref2, _ = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=0.08, sigma_n=0.3, separable=False)
    fast2, _ = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=0.08, sigma_n=0.3, separable=False,
                               filter_normals=False)
    assert np.allclose(fast2, ref2, atol=1e-6)


def test_colour_only_still_stops_at_the_crease():
    """A colour-uniform surface with a crease: the normals still stop the smoothing of a colour step there."""
    n = 64
    normals = np.zeros((n, n, 3), np.float32)
    normals[..., 2] = 1
    normals[:, n // 2:] = (0.8, 0.0, 0.6)
    albedo = np.full((n, n, 3), 0.3, np.float32)
    albedo[:, n // 2:] = 0.32                       # a colour step too small for sigma_c alone to stop
    out, _ = joint_bilateral(albedo, normals, sigma_x=3, sigma_c=1.0, sigma_n=0.1, filter_normals=False)
    blind, _ = joint_bilateral(albedo, None, sigma_x=3, sigma_c=1.0)
    step = lambda a: float(a[:, n // 2, 0].mean() - a[:, n // 2 - 1, 0].mean())  # noqa: E731
    assert step(out) > 0.9 * 0.02 and step(blind) < 0.8 * 0.02
