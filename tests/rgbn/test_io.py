import cv2
import numpy as np
import pytest
import tifffile

from common.rgbn.io import (encode_normal_map, linear_to_srgb, load_rgbn_files, read_albedo, read_normal_map,
                            srgb_to_linear, write_image)
from tests.rgbn.analytic import sphere


@pytest.mark.parametrize("suffix,bits", [(".png", 8), (".png", 16), (".tif", 8), (".tif", 16)])
def test_normal_map_round_trips_in_both_conventions(tmp_path, suffix, bits):
    n, mask = sphere(48, 2.0, 0.1)
    for convention in ("opengl", "directx"):
        path = tmp_path / f"n-{convention}{suffix}"
        write_image(path, encode_normal_map(n, mask, convention), bits=bits)
        back, back_mask = read_normal_map(path, convention)
        tol = 2.5 / (255 if bits == 8 else 65535) * 2
        assert np.array_equal(back_mask, mask)
        assert np.abs(back[mask] - n[mask]).max() < 2 * tol + 1e-4


def test_directx_green_channel_points_down(tmp_path):
    # a normal tilted towards the top of the image (y up) has a *low* green value in DirectX
    n = np.zeros((4, 4, 3), np.float32)
    n[...] = (0.0, 0.6, 0.8)
    path = tmp_path / "dx.png"
    write_image(path, encode_normal_map(n, convention="directx"))
    green = cv2.imread(str(path))[..., 1]
    assert (green < 128).all()
    back, _ = read_normal_map(path, "directx")
    assert np.allclose(back[..., 1], 0.6, atol=0.01)


def test_alpha_channel_and_black_background_are_outside_the_mask(tmp_path):
    n, mask = sphere(32, 1.5, 0.1)
    rgb = encode_normal_map(n, mask)
    alpha = np.ones((32, 32), np.float32)
    alpha[:, :4] = 0
    write_image(tmp_path / "a.png", rgb, alpha=alpha)
    _, got = read_normal_map(tmp_path / "a.png")
    assert np.array_equal(got, mask & (alpha > 0))


def test_albedo_is_decoded_from_srgb_and_must_share_the_grid(tmp_path):
    img = np.zeros((8, 8, 3), np.uint8)
    img[..., 0] = 188  # sRGB 188 -> linear ~0.5
    cv2.imwrite(str(tmp_path / "alb.png"), img[..., ::-1])
    albedo, _ = read_albedo(tmp_path / "alb.png")
    assert albedo[0, 0, 0] == pytest.approx(0.5, abs=0.01)
    n, mask = sphere(8, 0.4, 0.1)
    np.save(tmp_path / "n.npy", n)
    img8 = load_rgbn_files(tmp_path / "n.npy", tmp_path / "alb.png", dpi=600)
    assert img8.dpi == 600 and img8.albedo.shape == (8, 8, 3)
    np.save(tmp_path / "n9.npy", np.zeros((9, 9, 3), np.float32))
    with pytest.raises(ValueError, match="pixel grid"):
        load_rgbn_files(tmp_path / "n9.npy", tmp_path / "alb.png")


def test_srgb_transfer_round_trips():
    v = np.linspace(0, 1, 101, dtype=np.float32)
    assert np.allclose(srgb_to_linear(linear_to_srgb(v)), v, atol=1e-5)


def test_sixteen_bit_tiff_output_keeps_precision(tmp_path):
    ramp = np.tile(np.linspace(0, 1, 1000, dtype=np.float32), (2, 1))
    write_image(tmp_path / "r.tif", ramp, bits=16)
    data = tifffile.imread(tmp_path / "r.tif")
    assert data.dtype == np.uint16 and len(np.unique(data)) == 1000


def test_bad_convention_and_format_are_refused(tmp_path):
    with pytest.raises(ValueError, match="convention"):
        read_normal_map(tmp_path / "x.png", "vulkan")
    with pytest.raises(ValueError, match=r"\.png"):
        write_image(tmp_path / "x.bmp", np.zeros((2, 2)))


def _relief_normals(size=128, seed=0):
    """Normals of a random smooth height field (a surface with relief in every direction)."""
    rng = np.random.default_rng(seed)
    h = cv2.GaussianBlur(rng.standard_normal((size, size)).astype(np.float32), (0, 0), 4) * 30
    gy, gx = np.gradient(h)
    # rows go down, y up: dz/dy = -dz/drow
    n = np.stack([-gx, gy, np.ones_like(gx)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def test_the_y_convention_is_detected_from_the_curl_of_the_normal_field(tmp_path):
    from common.rgbn.io import detect_convention, encode_normal_map, read_normal_map, write_image

    n = _relief_normals()
    conv, evidence = detect_convention(n)
    assert conv == "opengl" and evidence["ratio"] > 2
    flipped = n.copy()
    flipped[..., 1] *= -1
    assert detect_convention(flipped)[0] == "directx"
    # through a file: a DirectX map read with "auto" gives Tessera's (OpenGL) normals back
    write_image(tmp_path / "dx.png", encode_normal_map(n, convention="directx"), bits=16)
    back, mask = read_normal_map(tmp_path / "dx.png", "auto")
    assert mask.all() and np.abs(back - n).max() < 1e-3


def test_a_surface_without_relief_leaves_the_convention_undecided():
    from common.rgbn.io import detect_convention

    n = np.zeros((64, 64, 3), np.float32)
    n[..., 2] = 1
    conv, evidence = detect_convention(n)
    assert conv == "opengl" and "undecided" in evidence.get("note", "")


def test_a_photograph_is_refused_as_a_normal_map_with_the_reason(tmp_path):
    from common.rgbn.io import read_normal_map

    rng = np.random.default_rng(1)
    photo = cv2.GaussianBlur(rng.uniform(0, 255, (64, 64, 3)).astype(np.float32), (0, 0), 3)
    photo = np.clip((photo - photo.mean()) * 4 + 110, 0, 255).astype(np.uint8)  # a brownish picture
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    with pytest.raises(ValueError, match=r"photo\.png does not look like a normal map"):
        read_normal_map(tmp_path / "photo.png")


def test_srgb_transfer_is_the_iec_formula_for_every_memory_layout():
    """IEC 61966-2-1 written out, for C-ordered, channel-reversed (BGR -> RGB), transposed and
    strided inputs: a layout without a flat view once lost the power (the values came back
    unpowered)."""
    from common.rgbn.io import linear_to_srgb, srgb_to_linear

    x = np.random.default_rng(2).random((40, 30, 3))
    for a in (x, x[..., ::-1] / np.float32(1.0), x.transpose(1, 0, 2), x[:, ::2], np.asfortranarray(x)):
        a = np.asarray(a)
        decode = np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4)
        encode = np.where(a <= 0.0031308, a * 12.92, 1.055 * a ** (1 / 2.4) - 0.055)
        assert np.abs(srgb_to_linear(a) - decode).max() < 1e-6
        assert np.abs(linear_to_srgb(a) - encode).max() < 1e-6


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_a_written_image_declares_its_dpi_so_other_tools_measure_it_right(tmp_path, suffix):
    from PIL import Image

    from common.imports.resolution import resolve_dpi

    img = np.random.default_rng(0).random((20, 30, 3))
    path = write_image(tmp_path / f"a{suffix}", img, bits=16, alpha=np.ones((20, 30)), dpi=150.0)
    with Image.open(path) as im:
        assert im.info["dpi"] == pytest.approx((150.0, 150.0), rel=1e-4)   # PNG: whole pixels per metre
    assert resolve_dpi([path])[0] == pytest.approx(150.0, rel=1e-4)   # what `tessera import` reads back
    plain = write_image(tmp_path / f"b{suffix}", img, bits=16, alpha=np.ones((20, 30)))   # no dpi: none declared
    with Image.open(plain) as im:
        assert "dpi" not in im.info or im.info["dpi"] == pytest.approx((1.0, 1.0))
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)                  # the same pixels either way
    assert back.shape == (20, 30, 4) and back.dtype == np.uint16
    np.testing.assert_array_equal(back, cv2.imread(str(plain), cv2.IMREAD_UNCHANGED))
