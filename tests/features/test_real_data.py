"""The extractor on real fragments: DAFNE fresco fragments (colour only, eroded outlines)."""

import cv2
import numpy as np
import pytest

from common.features import extract_features, fragment_descriptors
from common.features.patches import MIN_COVERAGE
from common.rgbn.image import RGBNImage
from common.rgbn.io import srgb_to_linear

DPI = 50.0  # DAFNE has no physical scale; the nominal 50 dpi of common.synth.import_dafne


def _dafne(shared_data, i):
    rgba = cv2.imread(str(shared_data / "dafne-adam" / "fragments" / f"frag_eroded_{i}.png"), cv2.IMREAD_UNCHANGED)
    if rgba is None:
        pytest.skip(f"DAFNE fragment {i} not readable")
    albedo = srgb_to_linear(rgba[..., 2::-1] / 255.0)
    return RGBNImage(albedo, rgba[..., 3] > 127, DPI)


@pytest.mark.parametrize("i", [0, 7, 42, 101, 230])
def test_colour_only_real_fragments_give_colour_and_contour_cues_and_nan_for_the_rest(shared_data, i):
    img = _dafne(shared_data, i)
    t = extract_features(img)
    assert t.missing_data == ["height", "normal"]
    for d in fragment_descriptors():
        assert np.isfinite(t.values[d.name]) == (not d.needs & {"normal", "height"}), d.name
    # the fragment's mean colour is the mean of its linear pixels (an independent computation)
    assert t.values["colour_mean_g"] == pytest.approx(float(img.albedo[img.mask, 1].mean()), abs=1e-4)
    # the traced outline encloses the fragment's area (shoelace vs pixel count)
    x, y = t.contour_mm.T
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    assert area == pytest.approx(img.mask.sum() * img.pixel_mm ** 2, rel=0.05)
    if t.n_patches:
        assert np.isfinite(t.patch_column("curv_3pt_5")).all()
        ok = t.patch_coverage >= MIN_COVERAGE
        assert np.isfinite(t.patch_column("colour_mean_r")[ok]).all()
