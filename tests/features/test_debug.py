"""Debug pictures (common/features/debug.py)."""

import cv2
import numpy as np

from common.features import extract_features
from common.features.debug import save_debug_pictures
from common.rgbn.image import RGBNImage


def _image(normals=True):
    yy, xx = np.mgrid[:160, :160]
    mask = (yy - 80) ** 2 + (xx - 80) ** 2 < 70 ** 2
    n = np.zeros((160, 160, 3), np.float32)
    n[..., 1] = 0.2 * np.sin(2 * np.pi * yy / 10)
    n[..., 2] = 1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return RGBNImage(np.full((160, 160, 3), 0.5), mask, 100.0, normals=n if normals else None)


def test_pictures_are_written_and_readable(tmp_path):
    img = _image()
    paths = save_debug_pictures(img, extract_features(img), tmp_path, prefix="f-")
    assert [p.name for p in paths] == ["f-patches.png", "f-orientation.png", "f-erosion.png"]
    for p in paths:
        pic = cv2.imread(str(p))
        assert pic is not None and pic.shape[0] > 200 and p.stat().st_size < 300_000


def test_colour_only_image_gets_the_patch_picture_only(tmp_path):
    img = _image(normals=False)
    paths = save_debug_pictures(img, extract_features(img), tmp_path)
    assert [p.name for p in paths] == ["patches.png"]
