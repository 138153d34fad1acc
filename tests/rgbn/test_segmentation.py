import numpy as np
import pytest

from common.rgbn.image import RGBNImage
from common.rgbn.segmentation import segment_means, segment_rgbn, segment_source
from tests.rgbn.analytic import tilted_plane


def two_orientations(size=64):
    n = tilted_plane(size, 0)
    n[:, size // 2:] = tilted_plane(size, 40, 0)[:, size // 2:]
    return n


def test_regions_differing_only_in_normal_are_separated():
    n = two_orientations()
    albedo = np.full(n.shape, 0.5, np.float32)  # identical colour everywhere
    labels = segment_rgbn(albedo, n, scale=20, sigma_px=0.5, min_size=200)
    left, right = labels[:, :30], labels[:, 34:]
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert left[0, 0] != right[0, 0]


def test_colour_only_segmentation_cannot_see_a_normal_edge():
    n = two_orientations()
    albedo = np.full(n.shape, 0.5, np.float32)
    labels = segment_rgbn(albedo, n, scale=20, sigma_px=0.5, min_size=200, normal_weight=0.0)
    assert len(np.unique(labels)) == 1


def test_regions_differing_only_in_colour_are_separated():
    albedo = np.full((48, 48, 3), 0.2, np.float32)
    albedo[24:] = (0.7, 0.3, 0.2)
    labels = segment_rgbn(albedo, tilted_plane(48, 0), scale=20, sigma_px=0.5, min_size=100)
    assert labels[0, 0] != labels[-1, 0]
    assert len(np.unique(labels[:20])) == 1 and len(np.unique(labels[28:])) == 1


def test_labels_are_ordered_by_area_and_minus_one_outside_the_mask():
    n = two_orientations()
    n[:, 48:] = tilted_plane(64, 40, 180)[:, 48:]
    mask = np.ones((64, 64), bool)
    mask[:4] = False
    labels = segment_rgbn(None, n, mask=mask, scale=20, sigma_px=0, min_size=50)
    assert (labels[~mask] == -1).all()
    counts = np.bincount(labels[mask])
    assert list(counts) == sorted(counts, reverse=True) and len(counts) == 3


def test_segment_means_average_within_each_segment():
    labels = np.array([[0, 0, 1], [0, 1, -1]])
    values = np.array([[1.0, 3.0, 10.0], [2.0, 20.0, 7.0]])
    out = segment_means(values, labels)
    assert np.allclose(out, [[2.0, 2.0, 15.0], [2.0, 15.0, 7.0]])


def test_bad_weights_are_refused_by_name():
    with pytest.raises(ValueError, match="normal_weight"):
        segment_rgbn(None, tilted_plane(8), normal_weight=-1)
    with pytest.raises(ValueError, match="nothing to segment"):
        segment_rgbn(None, None)


def test_large_images_are_segmented_on_a_coarser_grid_with_the_same_regions():
    n = two_orientations(128)
    mask = np.ones((128, 128), bool)
    mask[:, :3] = False
    full = segment_rgbn(None, n, mask=mask, scale=20, sigma_px=0, min_size=400, max_megapixels=None)
    coarse = segment_rgbn(None, n, mask=mask, scale=20, sigma_px=0, min_size=400, max_megapixels=0.004)
    assert (coarse[~mask] == -1).all() and (coarse[mask] >= 0).all()
    # the same two regions, boundaries within the downsampling factor (3 px)
    agree = (full == coarse)[:, 3:]
    assert agree.mean() > 0.95 and agree[:, :58].all() and agree[:, 67:].all()


def test_a_fragment_with_a_background_margin_is_segmented_inside_its_box_only():
    n = two_orientations(64)
    mask = np.zeros((64, 64), bool)
    mask[20:44, 10:54] = True
    labels = segment_rgbn(None, n, mask=mask, scale=20, sigma_px=0, min_size=50)
    assert (labels[~mask] == -1).all()
    assert labels[30, 15] != labels[30, 50] and len(np.unique(labels[mask])) == 2


def _quadrants(size=600, seed=0):
    """Four regions: two orientations (left/right) x two colours (top/bottom), with noise."""
    rng = np.random.default_rng(seed)
    n = two_orientations(size)
    n = n + rng.normal(0, 0.01, n.shape).astype(np.float32)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    albedo = np.full(n.shape, 0.5, np.float32)
    albedo[size // 2:] = (0.7, 0.3, 0.2)
    albedo += rng.normal(0, 0.01, albedo.shape).astype(np.float32)
    return RGBNImage(albedo=albedo, mask=np.ones((size, size), bool), dpi=600.0, normals=n)


def test_window_by_window_segmentation_is_the_whole_images():
    from common.render.tiles import MemorySource

    img = _quadrants()
    # min_size above the 1-2 px strips the pre-smoothing ramps make along the 600-px boundaries
    kw = dict(scale=400.0, sigma_px=1.0, min_size=2000)
    whole = segment_rgbn(img.albedo, img.normals, mask=img.mask, **kw)
    # superpixels in one SLIC window: the same labels, exactly (windows blurred with a halo)
    assert np.array_equal(segment_source(MemorySource(img), **kw), whole)
    # SLIC in 256-px windows, merged across their seams: the same four regions
    tiled = segment_source(MemorySource(img), tile=256, **kw)
    assert tiled.dtype == np.int32 and len(np.unique(whole)) == 4 and len(np.unique(tiled)) == 4
    inner = np.ones(whole.shape, bool)
    inner[295:305] = inner[:, 295:305] = False  # away from the true boundaries (at 300)
    assert (tiled[inner] == whole[inner]).all()
    # the quadrants' labels by area are the generator's regions
    for r, c in ((100, 100), (100, 500), (500, 100), (500, 500)):
        assert len(np.unique(tiled[r - 90:r + 90, c - 90:c + 90])) == 1


def test_window_by_window_segmentation_keeps_minus_one_outside_the_mask_and_refuses_bad_numbers():
    from common.render.tiles import MemorySource

    img = _quadrants()
    img.mask[:, :40] = False
    labels = segment_source(MemorySource(img), tile=256, scale=400.0, sigma_px=1.0, min_size=400)
    assert (labels[:, :40] == -1).all() and (labels[:, 40:] >= 0).all()
    with pytest.raises(ValueError, match="min_size"):
        segment_source(MemorySource(img), min_size=0)


def _flat_regions(size=640, seed=0):
    """Four flat regions with known boundaries off the 2-px block grid of the superpixels: two
    colours split at an odd column, a disc of a third colour on the left, and on the right a disc
    that differs from its surround in orientation only; 1 % noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    truth = np.where(xx < 301, 0, 1)
    truth[(yy - 211.5) ** 2 + (xx - 150.0) ** 2 < 97.5 ** 2] = 2
    truth[(yy - 420.0) ** 2 + (xx - 470.5) ** 2 < 110.0 ** 2] = 3
    colours = np.array([(0.7, 0.6, 0.45), (0.35, 0.3, 0.25), (0.6, 0.2, 0.1), (0.35, 0.3, 0.25)], np.float32)
    tilt = np.deg2rad(35.0)
    normals = np.array([(0, 0, 1), (0, 0, 1), (0, 0, 1), (np.sin(tilt), 0, np.cos(tilt))], np.float32)
    albedo = colours[truth] + rng.normal(0, 0.01, (size, size, 3)).astype(np.float32)
    n = normals[truth] + rng.normal(0, 0.01, (size, size, 3)).astype(np.float32)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    return albedo, n, truth


def test_flat_regions_are_recovered_to_within_a_pixel_of_their_boundaries():
    import scipy.ndimage as ndi

    albedo, n, truth = _flat_regions()
    # 0.41 Mpx: the superpixel path, SLIC on 2 x 2 blocks with the boundaries placed per pixel
    labels = segment_rgbn(albedo, n, scale=400.0, sigma_px=1.0, min_size=1000)
    assert labels.max() + 1 == 4
    mapping = np.array([np.bincount(labels[truth == r]).argmax() for r in range(4)])
    assert len(set(mapping)) == 4
    wrong = labels != mapping[truth]
    edge = np.zeros(truth.shape, bool)
    edge[:, 1:] |= truth[:, 1:] != truth[:, :-1]
    edge[1:] |= truth[1:] != truth[:-1]
    # every mislabelled pixel is at most 1 px from a true boundary (the pixel either side of it)
    assert ndi.distance_transform_edt(~edge)[wrong].max(initial=0) <= 1.5
    assert wrong.mean() < 0.001
