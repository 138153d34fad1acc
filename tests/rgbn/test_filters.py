import cv2
import numpy as np
import pytest

from common.rgbn._filters import decimated_sigma, decimation_factor, gaussian_blur, upsampled_rows


@pytest.mark.parametrize("factor", [2, 4, 8])
def test_upsampled_rows_are_the_rows_of_the_whole_bilinear_resize(factor):
    rng = np.random.default_rng(factor)
    for hh, ww, c in ((37, 29, 4), (5, 7, 1), (1, 3, 4), (60, 50, 3)):
        small = rng.random((hh, ww, c), dtype=np.float32)
        small = small[..., 0] if c == 1 else small
        h, w = hh * factor, ww * factor
        whole = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
        for r0, r1 in ((0, h), (0, 1), (h - 1, h), (1, min(h, 17)), (factor - 1, min(h, 2 * factor + 1))):
            got = upsampled_rows(small, (h, w), (r0, r1))
            assert np.array_equal(got.reshape(whole[r0:r1].shape), whole[r0:r1])


@pytest.mark.parametrize("sigma", [6.0, 9.0, 20.0])
def test_a_blur_on_a_downsampled_copy_damps_a_sinusoid_as_the_gaussian_does(sigma):
    """Analytic: a Gaussian multiplies a sinusoid of angular frequency k by exp(-k^2 sigma^2 / 2);
    the downsampled blur (box, blur at decimated_sigma, bilinear tent) does so within 1 % of the
    amplitude away from the borders."""
    size = 512
    assert decimation_factor(sigma, (size, size)) >= 2
    x = np.arange(size, dtype=np.float32)
    for period in (4 * sigma, 8 * sigma):
        k = 2 * np.pi / period
        img = np.tile(np.sin(k * x), (64, 1)).astype(np.float32)
        got = gaussian_blur(img, sigma)[32, 128:-128]
        expect = np.exp(-0.5 * (k * sigma) ** 2) * np.sin(k * x[128:-128])
        assert np.abs(got - expect).max() < 0.01


def test_decimated_sigma_makes_up_the_box_and_the_tent():
    """(f^2 - 1) / 12 + f^2 / 6 + (f s)^2 = sigma^2 (box, tent and the grid's blur add up)."""
    for sigma, f in ((6.0, 2), (13.0, 4), (40.0, 8)):
        s = decimated_sigma(sigma, f)
        assert (f * f - 1) / 12 + f * f / 6 + (f * s) ** 2 == pytest.approx(sigma ** 2)
