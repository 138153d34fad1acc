"""fragment_from_image: masks from alpha and from a plain background against a known fragment."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.imports import ImportRefused
from common.imports.fragments import background_mask, edge_coverage, fragment_from_image
from common.rgbn.io import srgb_to_linear


def _shape(h=300, w=400, seed=0):
    """Ground truth: an irregular polygon (a fragment outline) with a hole-free interior, (H, W) bool."""
    rng = np.random.default_rng(seed)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 11))
    rad = rng.uniform(0.25, 0.38, 11) * min(h, w)
    pts = np.stack([w / 2 + rad * np.cos(ang), h / 2 + rad * np.sin(ang)], axis=1).astype(np.int32)
    m = np.zeros((h, w), np.uint8)
    cv2.fillPoly(m, [pts], 1)
    return m > 0


def _paint(mask, seed=0):
    """Fresco-like paint inside (8-bit sRGB): an ochre field, a dark red band, a pale spot."""
    rng = np.random.default_rng(seed)
    h, w = mask.shape
    img = np.empty((h, w, 3), np.float32)
    img[:] = (190, 140, 80)
    img[:, w // 3: w // 3 + 30] = (110, 30, 25)
    cv2.circle(img, (w // 2, h // 2), 25, (235, 225, 205), -1)
    return np.clip(img + rng.normal(0, 6, img.shape), 0, 255), mask


def _iou(a, b):
    return (a & b).sum() / (a | b).sum()


@pytest.mark.parametrize("bg", [(245, 245, 240), (20, 20, 24), (40, 90, 160)])
def test_plain_background_mask_matches_ground_truth(bg):
    truth = _shape()
    paint, _ = _paint(truth)
    h, w = truth.shape
    # a lamp gradient of 30 levels across the picture and sensor noise on the background
    ramp = np.linspace(-15, 15, w, dtype=np.float32)[None, :, None]
    back = np.asarray(bg, np.float32) + ramp + np.random.default_rng(3).normal(0, 3, (h, w, 3))
    img = np.where(truth[..., None], paint, back)
    img = np.clip(img, 0, 255).astype(np.uint8)
    frag = fragment_from_image(img, dpi=300)
    assert frag.attrs["mask_from"] == "plain background"
    assert _iou(frag.mask, truth) > 0.98
    assert not frag.has_normals and frag.dpi == 300
    # albedo is linear (sRGB decoded) and zero outside the mask
    y, x = np.argwhere(truth & frag.mask)[len(np.argwhere(truth)) // 3]
    np.testing.assert_allclose(frag.albedo[y, x], srgb_to_linear(img[y, x] / 255.0), atol=1e-6)
    assert frag.albedo[~frag.mask].max() == 0


def test_sixteen_bit_picture_gives_the_same_mask():
    truth = _shape(seed=2)
    paint, _ = _paint(truth, seed=2)
    img8 = np.where(truth[..., None], paint, 250).astype(np.uint8)
    f8 = fragment_from_image(img8, dpi=600)
    f16 = fragment_from_image(img8.astype(np.uint16) * 257, dpi=600)
    assert _iou(f8.mask, f16.mask) > 0.999
    np.testing.assert_allclose(f8.albedo, f16.albedo, atol=1e-5)


def test_soft_alpha_edge_is_split_at_half_coverage():
    truth = _shape(seed=1)
    # a 4-pixel soft edge: alpha = smooth ramp across the outline, 0.5 exactly on it
    inside = cv2.distanceTransform(truth.astype(np.uint8), cv2.DIST_L2, 5)
    outside = cv2.distanceTransform((~truth).astype(np.uint8), cv2.DIST_L2, 5)
    signed = np.where(truth, inside - 0.5, -(outside - 0.5))
    alpha = np.clip(0.5 + signed / 4.0, 0, 1)
    paint, _ = _paint(truth, seed=1)
    rgba = np.dstack([paint * (alpha[..., None] > 0), alpha * 255]).astype(np.uint8)   # black outside
    frag = fragment_from_image(rgba, dpi=150)
    assert frag.attrs["mask_from"] == "alpha"
    assert _iou(frag.mask, truth) > 0.99
    np.testing.assert_array_equal(frag.mask, rgba[..., 3] > 127)


def test_opaque_alpha_falls_back_to_the_background():
    truth = _shape(seed=4)
    paint, _ = _paint(truth, seed=4)
    rgb = np.where(truth[..., None], paint, 240).astype(np.uint8)
    rgba = np.dstack([rgb, np.full(truth.shape, 255, np.uint8)])
    frag = fragment_from_image(rgba, dpi=300)
    assert frag.attrs["mask_from"] == "plain background" and _iou(frag.mask, truth) > 0.98
    with pytest.raises(ImportRefused, match="no fragment found.*alpha"):
        fragment_from_image(rgba * np.array([1, 1, 1, 0], np.uint8), dpi=300, background="alpha")



def test_alpha_never_below_half_coverage_falls_back_to_the_background():
    # docs/import.md: auto takes the alpha when it cuts something out (some pixel at or below half
    # coverage), not whenever it is not opaque everywhere: alpha > 50 % would keep the whole frame
    truth = _shape(seed=5)
    paint, _ = _paint(truth, seed=5)
    rgb = np.where(truth[..., None], paint, 240).astype(np.uint8)
    alpha = np.full(truth.shape, 255, np.uint8)
    alpha[:40, :40] = 200                     # a translucent corner, ~78 % coverage
    frag = fragment_from_image(np.dstack([rgb, alpha]), dpi=300)
    assert frag.attrs["mask_from"] == "plain background" and _iou(frag.mask, truth) > 0.98

def test_implausible_pictures_are_refused_with_the_reason():
    rng = np.random.default_rng(0)
    plain = np.clip(200 + rng.normal(0, 3, (200, 300, 3)), 0, 255).astype(np.uint8)
    with pytest.raises(ImportRefused, match="no fragment found"):
        fragment_from_image(plain, dpi=300)
    # a piece cut off by the frame: the fragment runs out of the picture on the right
    cut = plain.copy()
    cut[40:160, 150:] = (120, 60, 40)
    with pytest.raises(ImportRefused, match="touches the picture's border"):
        fragment_from_image(cut, dpi=300)
    # a frame-filling picture: almost all of it differs from the border colour
    filled = np.full((200, 300, 3), (120, 60, 40), np.uint8)
    filled[:3], filled[-3:], filled[:, :3], filled[:, -3:] = 250, 250, 250, 250
    with pytest.raises(ImportRefused, match="cover 9[0-9] % of the picture"):
        fragment_from_image(filled, dpi=300)


def _reaching_the_bottom(touch_px, seed=0):
    """A 200x300 noisy picture on a plain background, the piece running out of it along ``touch_px`` of the bottom
    edge (the 1-pixel border has 996 pixels)."""
    rng = np.random.default_rng(seed)
    img = np.empty((200, 300, 3), np.float32)
    img[:] = (40, 40, 40)
    x0 = (300 - touch_px) // 2
    img[80:, x0:x0 + touch_px] = (200, 150, 90)
    return np.clip(np.round(img + rng.normal(0, 6, img.shape)), 0, 255).astype(np.uint8), x0


@pytest.mark.parametrize("touch_px", [170, 200, 250])
def test_a_piece_cut_off_by_the_frame_is_refused_as_such(touch_px):
    """docs/import.md: a piece touching more than 10 % of the picture's border is refused (cut off by the frame).
    With ~17 % or more of the border strip being fragment, the background fit took the piece for background (the
    3-MAD rule never dropped it, the threshold ended above full scale) and the refusal said "no fragment found
    (0.00 % ...; ... by more than 311/255)". The background is fitted to the border pixels nearest its median
    colour now, so the piece on the border cannot drag it."""
    img, _ = _reaching_the_bottom(touch_px)
    with pytest.raises(ImportRefused, match=r"touches the picture's border along (1[7-9]|2[0-9]) % of it"):
        fragment_from_image(img, dpi=300)
    mask, info = background_mask(img.astype(np.float32) / 255)
    np.testing.assert_allclose(np.array(info["background"]) * 255, 40, atol=1.5)   # the background, not a mix
    assert info["threshold"] * 255 < 60


def test_a_piece_touching_a_twentieth_of_the_border_is_imported():
    img, x0 = _reaching_the_bottom(50)            # 50 of 996 border pixels: 5 %
    frag = fragment_from_image(img, dpi=300)
    truth = np.zeros((200, 300), bool)
    truth[80:, x0:x0 + 50] = True
    assert _iou(frag.mask, truth) > 0.98


def test_bad_arguments_are_named():
    img = np.zeros((50, 50, 3), np.uint8)
    with pytest.raises(ValueError, match="dpi"):
        fragment_from_image(img, dpi=0)
    with pytest.raises(ValueError, match="background"):
        fragment_from_image(img, dpi=100, background="green")
    with pytest.raises(ValueError, match="alpha_threshold"):
        fragment_from_image(img, dpi=100, alpha_threshold=1.5)
    with pytest.raises(ValueError, match="no alpha channel"):
        fragment_from_image(img, dpi=100, background="alpha")
    with pytest.raises(ValueError, match="rgb must be"):
        background_mask(np.zeros((50, 50)))


def test_repair_dev_alpha_mask_is_alpha_over_half(shared_data):
    import glob
    paths = sorted(glob.glob(str(shared_data / "repair-dev" / "*" / "*.png")))
    if not paths:
        pytest.skip("repair-dev not present in ../shared/data")
    rgba = cv2.imread(paths[0], cv2.IMREAD_UNCHANGED)[..., [2, 1, 0, 3]]
    frag = fragment_from_image(rgba, dpi=187.2)
    np.testing.assert_array_equal(frag.mask, rgba[..., 3] > 127)
    # the same piece without its alpha, on its black background: the plain-background path
    plain = fragment_from_image(rgba[..., :3], dpi=187.2, background="plain")
    assert _iou(plain.mask, frag.mask) > 0.95


def _scanned(truth, paint_srgb, background_srgb, *, blur_px=1.0, noise=1.5, seed=0):
    """The piece as a scanner records it on a plain background: coverage mixed in linear light along
    a 1-px-antialiased outline, the optics' blur, sensor noise; uint8 sRGB."""
    from common.rgbn.io import linear_to_srgb
    cover = cv2.GaussianBlur(truth.astype(np.float32), (0, 0), 0.5)   # partial pixels on the outline
    lin = (srgb_to_linear(paint_srgb / 255.0) * cover[..., None]
           + srgb_to_linear(np.asarray(background_srgb, np.float32) / 255.0) * (1 - cover[..., None]))
    lin = cv2.GaussianBlur(lin.astype(np.float32), (0, 0), blur_px)
    noisy = linear_to_srgb(lin) * 255 + np.random.default_rng(seed).normal(0, noise, lin.shape)
    return np.clip(noisy + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("bg", [(0, 0, 0), (240, 238, 232), (40, 90, 160)])
def test_a_scanned_edge_is_placed_at_half_coverage_whatever_the_background(bg):
    # a low threshold finds the piece but puts its edge where it covers a few per cent of a pixel:
    # on black that was ~2.4 px outside the true outline. The edge is placed again by coverage,
    # so the outline does not depend on the background (mean offset = area difference / perimeter)
    truth = _shape(seed=6)
    paint, _ = _paint(truth, seed=6)
    img = _scanned(truth, paint, bg)
    mask, info = background_mask(img.astype(np.float32) / 255)
    perimeter = cv2.arcLength(cv2.findContours(truth.astype(np.uint8), cv2.RETR_EXTERNAL,
                                               cv2.CHAIN_APPROX_NONE)[0][0], True)
    offset_px = (int(mask.sum()) - int(truth.sum())) / perimeter
    assert abs(offset_px) < 0.35, offset_px
    assert info["edge_placed"] > 0.9 and _iou(mask, truth) > 0.99


def test_edge_coverage_of_a_blurred_step_is_the_blur_profile():
    # analytic case: a straight edge blurred by a Gaussian of sigma 1.2 px has coverage Phi(x / sigma)
    from scipy.stats import norm
    h, w, edge, sigma = 40, 60, 30.0, 1.2
    x = np.arange(w) + 0.5
    cover = norm.cdf((edge - x) / sigma)                     # the piece on the left
    f, b = np.array([0.8, 0.5, 0.3]), np.array([0.02, 0.02, 0.03])      # linear
    from common.rgbn.io import linear_to_srgb
    rgb = linear_to_srgb(np.broadcast_to(cover[None, :, None] * f + (1 - cover[None, :, None]) * b, (h, w, 3)))
    first = np.broadcast_to(x[None, :] < edge + 2.5, (h, w))      # a low threshold's edge, 2.5 px outside
    back = np.broadcast_to(linear_to_srgb(b), (h, w, 3))
    alpha = edge_coverage(rgb, first, back, edge_px=3)
    row = alpha[h // 2]
    band = np.isfinite(row) & (row > 0) & (row < 1)
    np.testing.assert_allclose(row[band], cover[band], atol=0.01)
    # the mixed pixels unmixed carry the piece's own colour, not a dark fringe
    from common.imports.fragments import unmix_edge
    own = unmix_edge(rgb, alpha, back)
    keep = (alpha[h // 2] >= 0.5) & (alpha[h // 2] < 1)
    assert keep.any()
    np.testing.assert_allclose(srgb_to_linear(own[h // 2, keep]), np.broadcast_to(f, (int(keep.sum()), 3)), atol=0.01)


def test_edge_of_too_little_contrast_keeps_the_threshold():
    # pale plaster on white paper: half coverage cannot be told from noise, so the edge is left where
    # the threshold found it (NaN coverage), not moved by noise
    truth = _shape(seed=7)
    img = _scanned(truth, np.full(truth.shape + (3,), (226.0, 224.0, 218.0)), (240, 238, 232), noise=1.0)
    mask, info = background_mask(img.astype(np.float32) / 255)
    assert info["edge_placed"] < 0.5
    assert np.isnan(info["coverage"]).any()
