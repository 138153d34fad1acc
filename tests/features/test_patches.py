"""Patch sampling along the contour (common/features/patches.py)."""

import numpy as np
import pytest

from common.features.contour import fragment_contour
from common.features.patches import disk_window, sample_patches


def test_patches_every_5mm_inset_along_the_inward_normal_of_a_disc():
    px = 0.25
    yy, xx = np.mgrid[:240, :240]
    R_px = 100
    mask = (yy - 120) ** 2 + (xx - 120) ** 2 < R_px ** 2
    c = fragment_contour(mask, px)
    p = sample_patches(c, mask, px)
    R = R_px * px
    n_pos = int(np.floor(2 * np.pi * R / 5.0))
    assert len(p) == 2 * n_pos
    for kind, inset in (("p10", 8.0), ("p20", 13.0)):
        sel = p.kind == kind
        dist = np.hypot(*(p.centers_mm[sel] - 120 * px).T)
        assert np.allclose(dist, R - inset, atol=0.2)
        assert np.allclose(np.diff(p.arc_mm[sel]), 5.0)
        assert np.allclose(p.coverage[sel], 1.0, atol=0.01)


def test_coverage_of_a_patch_half_off_a_straight_edge_is_one_half():
    px = 0.1
    mask = np.zeros((300, 300), np.float32)
    mask[:, :150] = 1.0
    rows, cols, w, full = disk_window((15.0 - 0.05, 15.0), 5.0, px, mask.shape)  # centre on the edge
    assert np.sum(w * mask[rows, cols]) / full == pytest.approx(0.5, abs=0.01)


def test_disc_running_off_the_image_counts_the_missing_part_as_off_fragment():
    rows, cols, w, full = disk_window((0.0, 0.0), 2.0, 0.1, (100, 100))
    assert w.sum() / full == pytest.approx(0.25, abs=0.03)


def test_bad_arguments_are_refused():
    c = fragment_contour(np.pad(np.ones((50, 50), bool), 5), 1.0)
    with pytest.raises(ValueError, match="spacing_mm"):
        sample_patches(c, np.ones((60, 60)), 1.0, spacing_mm=0)
    with pytest.raises(ValueError, match="coverage_map"):
        sample_patches(c, np.ones(60), 1.0)
