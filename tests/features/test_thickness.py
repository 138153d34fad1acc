"""Thickness (common/features/thickness.py)."""

import numpy as np
import pytest

from common.features.thickness import mean_thickness


def test_mean_over_finite_values_in_the_region():
    h = np.array([[10.0, 12.0], [np.nan, 20.0]])
    m = np.array([[True, True], [True, False]])
    assert mean_thickness(h, m) == pytest.approx(11.0)


def test_no_map_or_no_finite_value_is_missing():
    assert np.isnan(mean_thickness(None, np.ones((2, 2), bool)))
    assert np.isnan(mean_thickness(np.full((2, 2), np.nan), np.ones((2, 2), bool)))
    with pytest.raises(ValueError, match="same shape"):
        mean_thickness(np.ones((2, 2)), np.ones((3, 3), bool))
