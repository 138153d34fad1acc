"""Door checks: complete decodes or a refusal naming the file and the reason."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.imports import ImportRefused
from common.imports.door import read_image_checked, read_images_checked


def _photo(h=120, w=160, seed=0):
    """A textured RGB picture (uint8) with JPEG-sized detail."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 255 / w, y * 255 / h, 128 + 60 * np.sin(x / 7.0)], axis=2)
    return np.clip(base + rng.normal(0, 12, base.shape), 0, 255).astype(np.uint8)


def _write(path, rgb):
    assert cv2.imwrite(str(path), rgb[..., ::-1] if rgb.ndim == 3 and rgb.shape[2] == 3 else rgb)
    return path


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif"])
def test_complete_files_decode_in_rgb_order(tmp_path, suffix):
    rgb = _photo()
    img = read_image_checked(_write(tmp_path / f"a{suffix}", rgb))
    assert img.pixels.shape == rgb.shape and img.bits == 8 and img.full_scale == 255
    tol = 12 if suffix == ".jpg" else 0
    assert np.abs(img.pixels.astype(int) - rgb).mean() <= tol
    # channel order: red rises along x, green along y
    assert img.pixels[60, 150, 0] > img.pixels[60, 5, 0] and img.pixels[110, 80, 1] > img.pixels[5, 80, 1]


@pytest.mark.parametrize("suffix,cut", [(".png", 0.5), (".png", 0.98), (".jpg", 0.6), (".jpg", 0.97), (".tif", 0.5)])
def test_truncated_files_are_refused(tmp_path, suffix, cut):
    full = _write(tmp_path / f"full{suffix}", _photo(400, 400))
    data = full.read_bytes()
    bad = tmp_path / f"cut{suffix}"
    bad.write_bytes(data[:int(len(data) * cut)])
    if suffix == ".jpg":  # the trap this protects against: OpenCV decodes the damaged file without complaint
        assert cv2.imread(str(bad)) is not None
    with pytest.raises(ImportRefused, match=r"cut\.(png|jpg|tif).*(truncated|decoded)"):
        read_image_checked(bad)


def test_corrupt_png_chunk_is_refused(tmp_path):
    p = _write(tmp_path / "c.png", _photo())
    data = bytearray(p.read_bytes())
    data[len(data) // 2] ^= 0xFF
    p.write_bytes(bytes(data))
    with pytest.raises(ImportRefused, match="c.png.*CRC"):
        read_image_checked(p)


def test_black_and_blank_images_are_refused(tmp_path):
    black = _write(tmp_path / "black.png", np.zeros((50, 50, 3), np.uint8))
    grey = _write(tmp_path / "grey.png", np.full((50, 50, 3), 140, np.uint8))
    with pytest.raises(ImportRefused, match="black.png: is all black"):
        read_image_checked(black)
    with pytest.raises(ImportRefused, match="grey.png: is blank"):
        read_image_checked(grey)
    assert read_image_checked(black, allow_blank=True).pixels.max() == 0


def test_black_frame_with_hot_pixels_is_still_refused(tmp_path):
    # a frame taken with the lamp off: sensor noise near 0 and a few hot pixels at full scale
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 2, (200, 300, 3)).astype(np.uint8)
    frame[rng.integers(0, 200, 20), rng.integers(0, 300, 20)] = 255   # 20 hot pixels, 0.03 % of samples
    with pytest.raises(ImportRefused, match="hot.png: is all black"):
        read_image_checked(_write(tmp_path / "hot.png", frame))
    # a dark picture with a small lit object (1 % of the pixels) is not black
    dim = frame.copy()
    dim[90:110, 140:170] = 90
    assert read_image_checked(_write(tmp_path / "dim.png", dim)).pixels.shape == dim.shape


def test_bit_depth_is_checked(tmp_path):
    rgb = _photo()
    p8 = _write(tmp_path / "a8.png", rgb)
    p16 = _write(tmp_path / "a16.png", rgb.astype(np.uint16) * 257)
    fake16 = _write(tmp_path / "fake16.png", rgb.astype(np.uint16))   # 8-bit values in a 16-bit file
    assert read_image_checked(p16, bits=16).bits == 16
    with pytest.raises(ImportRefused, match="a8.png: is 8-bit but 16-bit was declared"):
        read_image_checked(p8, bits=16)
    with pytest.raises(ImportRefused, match="fake16.png: is a 16-bit file holding 8-bit values"):
        read_image_checked(fake16)


def test_channels_format_and_missing(tmp_path):
    grey = _write(tmp_path / "g.png", _photo()[..., 0])
    with pytest.raises(ImportRefused, match="g.png: has shape .* expected 3, 4 channels"):
        read_image_checked(grey, channels=(3, 4))
    txt = tmp_path / "notes.png"
    txt.write_text("hello")
    with pytest.raises(ImportRefused, match="notes.png: is not a PNG, JPEG, TIFF"):
        read_image_checked(txt)
    with pytest.raises(ImportRefused, match="nothere.png: does not exist"):
        read_image_checked(tmp_path / "nothere.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(ImportRefused, match="empty.png: is empty"):
        read_image_checked(tmp_path / "empty.png")



def test_npy_declaring_more_than_the_pixel_limit_is_refused_before_it_is_read(tmp_path):
    # docs/import.md: "more than 300 Mpx declared" is refused for every image read, .npy included
    # (np.load would allocate the whole declared array first)
    from numpy.lib import format as npy
    with open(tmp_path / "huge.npy", "wb") as fh:
        npy.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (20000, 20000, 3)})
        fh.write(b"\0" * 64)
    with pytest.raises(ImportRefused, match="huge.npy: declares 20000x20000 pixels, more than the limit"):
        read_image_checked(tmp_path / "huge.npy")
    np.save(tmp_path / "small.npy", np.linspace(0, 1, 40 * 30 * 3, dtype=np.float32).reshape(40, 30, 3))
    assert read_image_checked(tmp_path / "small.npy").pixels.shape == (40, 30, 3)

def test_a_list_must_agree_in_size_and_keeps_order(tmp_path):
    a = _write(tmp_path / "a.png", _photo(seed=1))
    b = _write(tmp_path / "b.png", _photo(seed=2))
    c = _write(tmp_path / "c.png", _photo(100, 160))
    imgs = read_images_checked([a, b], workers=2)
    assert [i.path.name for i in imgs] == ["a.png", "b.png"]
    with pytest.raises(ImportRefused, match="c.png: is 160x100 px but a.png is 160x120"):
        read_images_checked([a, b, c])
