"""Dominant orientation, eq. 5.4 (common/features/orientation.py)."""

import numpy as np
import pytest

from common.features.orientation import dominant_orientation


def _stripes(period_px, angle_deg, n=96, amp=0.02):
    yy, xx = np.mgrid[:n, :n]
    a = np.radians(angle_deg)
    u = xx * np.cos(a) + yy * np.sin(a)  # across the stripes, x right / y down
    return 0.95 + amp * np.cos(2 * np.pi * u / period_px)


@pytest.mark.parametrize("angle", [0.0, 25.0, 60.0, 90.0, 135.0])
def test_stripes_give_their_frequency_amplitude_and_direction(angle):
    px = 0.1
    d = dominant_orientation(_stripes(8.0, angle), np.ones((96, 96), bool), px, smooth_px=0)
    assert d["orient_frequency"] == pytest.approx(1 / (8.0 * px), rel=0.04)
    assert d["orient_amplitude"] == pytest.approx(0.02, rel=0.2)
    err = abs((d["orient_angle"] - angle + 90) % 180 - 90)
    assert err < 3.0


def test_angle_is_relative_to_the_reference_normal():
    z = _stripes(8.0, 30.0)
    n = (np.cos(np.radians(100.0)), np.sin(np.radians(100.0)))
    d = dominant_orientation(z, np.ones((96, 96), bool), 0.1, smooth_px=0, reference_normal=n)
    assert abs((d["orient_angle"] - (30.0 - 100.0) % 180 + 90) % 180 - 90) < 3.0


def test_frequencies_below_omega_min_are_ignored():
    # a strong 1-cycle wave and a weaker 10-cycle wave: the 1-cycle one is below omega_min = 3
    yy, xx = np.mgrid[:96, :96]
    z = 0.9 + 0.05 * np.cos(2 * np.pi * xx / 96) + 0.02 * np.cos(2 * np.pi * 10 * yy / 96)
    d = dominant_orientation(z, np.ones((96, 96), bool), 1.0, smooth_px=0)
    assert d["orient_frequency"] == pytest.approx(10 / 96, rel=0.05)
    assert abs(d["orient_angle"] - 90) < 3


def test_region_outline_does_not_make_a_peak_and_empty_region_is_missing():
    yy, xx = np.mgrid[:96, :96]
    disc = (yy - 48) ** 2 + (xx - 48) ** 2 < 40 ** 2
    z = np.where(disc, _stripes(12.0, 45.0), 0.0)  # background would dominate without the fill
    d = dominant_orientation(z, disc, 0.1, smooth_px=0)
    assert d["orient_frequency"] == pytest.approx(1 / 1.2, rel=0.06)
    assert np.isnan(dominant_orientation(z, np.zeros((96, 96), bool), 0.1)["orient_frequency"])
    with pytest.raises(ValueError, match="pixel_mm"):
        dominant_orientation(z, disc, 0.0)
