"""Segmentation of RGBN images by colour and normal (§7.2.4)."""

from __future__ import annotations

import warnings

import numpy as np
from skimage.segmentation import felzenszwalb

from common.rgbn._filters import check_mask, check_normals, gaussian_blur


def segment_rgbn(albedo: np.ndarray | None, normals: np.ndarray | None, *, mask: np.ndarray | None = None,
                 scale: float = 1.0, sigma_px: float = 0.8, min_size: int = 64,
                 colour_weight: float = 1.0, normal_weight: float = 1.0,
                 max_megapixels: float | None = None, superpixel_px="auto") -> np.ndarray:
    """Graph-based (Felzenszwalb-Huttenlocher) segmentation with a colour+normal dissimilarity.

    The edge weight between 4-/8-connected neighbours p, q is (§7.2.4)::

        d(p, q) = sqrt( wc^2 |c_p - c_q|^2 + wn^2 |n_p - n_q|^2 )

    so two regions that differ only in orientation (a fold, a broken face) separate as readily
    as regions of different colour. The minimum-spanning-forest merging with the adaptive
    threshold ``Int(C) + scale / |C|`` is scikit-image's implementation (Felzenszwalb &
    Huttenlocher 2004), fed with the weighted colour+normal channels.

    Parameters
    ----------
    albedo : (H, W, 3) float or None
        Colour in [0, 1]; None segments by normals only.
    normals : (H, W, 3) float or None
        Unit normals; None segments by colour only.
    mask : (H, W) bool, optional
        Pixels to segment; the rest get label -1.
    scale : float
        The paper's ``k``: larger values give fewer, larger segments (renamed as in scikit-image).
    sigma_px : float
        Gaussian pre-smoothing of the channels in pixels.
    min_size : int
        Minimum segment size in pixels (smaller ones are merged into a neighbour).
    colour_weight, normal_weight : float
        ``wc`` and ``wn`` above: the relative importance of colour and normal differences.
    max_megapixels : float or None
        Larger images are segmented on an integer-factor downsampled grid (area averaging, with
        ``min_size`` scaled accordingly) and the labels upsampled by nearest neighbour. None (the
        default) works at full resolution.
    superpixel_px : int, "auto" or None
        Full-resolution segmentation of a large image goes through superpixels: SLIC
        (Achanta et al. 2012, scikit-image's compiled implementation, on the weighted
        colour+normal channels, in 2048-px windows blurred with a halo; :func:`segment_source`
        reads them one at a time from an image larger than memory) cuts the image into regions of
        about this many pixels, and Felzenszwalb-Huttenlocher's merging runs on their adjacency
        graph with the distance between region means as the edge weight and region areas in
        pixels. SLIC clusters the means of f x f pixel blocks (f = 2 for 64-px superpixels:
        at least 16 blocks a superpixel), and the pixels of the blocks on a boundary between two
        superpixels that the merging criterion would keep apart go to the nearest superpixel mean
        around them, so boundaries are placed per pixel (:func:`_superpixel_tile`).
        "auto": 64-pixel superpixels above 0.25 Mpx, the pixel graph below. None: always the
        pixel graph (about 5 CPU s/Mpx with six channels, and ~500 bytes a pixel).

    Returns
    -------
    (H, W) int32
        Labels 0..K-1 ordered by decreasing area (0 = largest segment); -1 outside the mask.

    References
    ----------
    Toler-Franklin 2011, §7.2.4; P. Felzenszwalb, D. Huttenlocher, "Efficient graph-based image
    segmentation", IJCV 59(2), 2004; R. Achanta et al., "SLIC superpixels compared to
    state-of-the-art superpixel methods", IEEE TPAMI 34(11), 2012.

    Notes
    -----
    The paper's ``k`` is ``scale`` here; like the reference implementation on 8-bit images,
    scikit-image divides it by 255, so ``scale`` is in units of 1/255 of the dissimilarity ``d``.
    Pre-smoothing turns a sharp step into a ramp whose one-pixel strips become segments of their
    own unless ``min_size`` exceeds a strip's length.

    Examples
    --------
    >>> n = np.zeros((32, 32, 3), np.float32); n[..., 2] = 1; n[:, 16:] = (0.6, 0, 0.8)
    >>> labels = segment_rgbn(None, n, scale=1.0, sigma_px=0, min_size=10)
    >>> len(np.unique(labels)), bool(labels[0, 0] != labels[0, 31])
    (2, True)
    """
    if albedo is None and normals is None:
        raise ValueError("albedo and normals are both None: nothing to segment")
    parts, shape = [], None
    if albedo is not None:
        albedo = np.asarray(albedo, dtype=np.float32)
        if albedo.ndim != 3 or albedo.shape[2] != 3:
            raise ValueError(f"albedo must be (H, W, 3), got shape {albedo.shape}")
        shape = albedo.shape[:2]
        if colour_weight < 0:
            raise ValueError(f"colour_weight must be >= 0, got {colour_weight}")
        if colour_weight > 0:
            parts.append((albedo, np.float32(colour_weight)))
    if normals is not None:
        normals = check_normals(normals)
        if shape is not None and normals.shape[:2] != shape:
            raise ValueError(f"normals shape {normals.shape[:2]} differs from albedo shape {shape}")
        shape = normals.shape[:2]
        if normal_weight < 0:
            raise ValueError(f"normal_weight must be >= 0, got {normal_weight}")
        if normal_weight > 0:
            parts.append((normals, np.float32(normal_weight)))
    if not parts:
        raise ValueError("colour_weight and normal_weight are both 0: no dissimilarity to segment by")
    superpixel_px = _check_params(shape, scale, sigma_px, min_size, superpixel_px)
    mask = check_mask(mask, shape)
    if max_megapixels is not None and shape[0] * shape[1] > max_megapixels * 1e6:
        return _segment_downsampled(albedo, normals, mask, shape, scale=scale, sigma_px=sigma_px, min_size=min_size,
                                    colour_weight=colour_weight, normal_weight=normal_weight,
                                    max_megapixels=max_megapixels)
    if not mask.any():
        return np.full(shape, -1, np.int32)
    if not mask.all():
        # the graph of the fragment's bounding box only (scans carry a background margin)
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        box = (slice(max(rows[0] - 1, 0), rows[-1] + 2), slice(max(cols[0] - 1, 0), cols[-1] + 2))
        if mask[box].size < 0.9 * mask.size:
            out = np.full(shape, -1, np.int32)
            out[box] = segment_rgbn(None if albedo is None else albedo[box], None if normals is None else normals[box],
                                    mask=mask[box], scale=scale, sigma_px=sigma_px, min_size=min_size,
                                    colour_weight=colour_weight, normal_weight=normal_weight, max_megapixels=None)
            return out
    if superpixel_px is not None:
        h, w = shape
        return _segment_superpixels(_feature_windows(lambda r0, r1, c0, c1: (
            [None if v is None else v[r0:r1, c0:c1] for v in (albedo, normals)], mask[r0:r1, c0:c1]),
            shape, sigma_px, colour_weight, normal_weight), shape, scale=scale, min_size=min_size,
            superpixel_px=float(superpixel_px))
    feats = np.concatenate([values * weight for values, weight in parts], axis=2)
    if not mask.all():
        # background becomes one far-away constant so no segment straddles the mask border
        far = np.float32(10.0 * (abs(colour_weight) + abs(normal_weight)) + 10.0)
        feats = np.where(mask[..., None], feats, far)
    if sigma_px > 0:
        # OpenCV's float32 Gaussian is several times faster than the float64 one inside skimage
        feats = gaussian_blur(feats, float(sigma_px))
    with warnings.catch_warnings():
        # skimage warns that a 6-channel image "may not be intended": here it is
        warnings.filterwarnings("ignore", message="Got image with third dimension", category=RuntimeWarning)
        labels = felzenszwalb(feats.astype(np.float64), scale=float(scale), sigma=0.0,
                              min_size=int(min_size), channel_axis=-1)
    return _relabel_by_area(labels, mask)


def _check_params(shape, scale, sigma_px, min_size, superpixel_px):
    """Refuse bad [segmentation] numbers by name; returns superpixel_px with "auto" resolved."""
    if not scale > 0:
        raise ValueError(f"scale must be > 0, got {scale}")
    if min_size < 1:
        raise ValueError(f"min_size must be >= 1, got {min_size}")
    if sigma_px < 0:
        raise ValueError(f"sigma_px must be >= 0, got {sigma_px}")
    if superpixel_px == "auto":
        superpixel_px = 64 if shape[0] * shape[1] > 0.25e6 else None
    if superpixel_px is not None and (isinstance(superpixel_px, bool) or not isinstance(superpixel_px, (int, float))
                                      or superpixel_px < 4):
        raise ValueError(f'superpixel_px must be a number >= 4, "auto" or None, got {superpixel_px!r}')
    return superpixel_px


def segment_source(source, *, scale: float = 1.0, sigma_px: float = 0.8, min_size: int = 64,
                   colour_weight: float = 1.0, normal_weight: float = 1.0, max_megapixels: float | None = None,
                   superpixel_px="auto", tile: int = 2048) -> np.ndarray:
    """:func:`segment_rgbn` of an image read window by window, in bounded memory.

    ``source`` has ``shape`` and ``window(r0, r1, c0, c1) -> RGBNImage`` (as
    :class:`common.render.tiles.MemorySource` and ``H5Source``). On the superpixel path the
    colour and normals are read, blurred (with a halo, so the result is the whole-image blur's)
    and cut into SLIC superpixels (on f x f blocks, boundaries placed per pixel: see
    ``superpixel_px``) one ``tile`` x ``tile`` window at a time, and only the (H, W) int32 label
    map (4 bytes a pixel) and a few numbers per superpixel are kept for the merging.
    Small images (the pixel graph), ``superpixel_px=None`` and ``max_megapixels`` read the whole
    image and call :func:`segment_rgbn`. Parameters and labels as :func:`segment_rgbn`; the SLIC
    tiles start at the image's corner (:func:`segment_rgbn` starts them at the corner of the
    fragment's bounding box when the mask leaves a wide margin, so the two can differ there).
    """
    h, w = source.shape
    superpixel_px = _check_params((h, w), scale, sigma_px, min_size, superpixel_px)
    kw = dict(scale=scale, sigma_px=sigma_px, min_size=min_size, colour_weight=colour_weight,
              normal_weight=normal_weight)
    if superpixel_px is None or (max_megapixels is not None and h * w > max_megapixels * 1e6):
        im = source.window(0, h, 0, w)
        return segment_rgbn(im.albedo, im.normals, mask=im.mask, max_megapixels=max_megapixels,
                            superpixel_px=superpixel_px, **kw)
    probe = source.window(0, 1, 0, 1)
    if colour_weight < 0 or normal_weight < 0:
        raise ValueError(f"colour_weight and normal_weight must be >= 0, got {colour_weight}, {normal_weight}")
    if not ((probe.albedo is not None and colour_weight > 0) or (probe.normals is not None and normal_weight > 0)):
        raise ValueError("no colour or normals with a weight > 0: no dissimilarity to segment by")

    def read(r0, r1, c0, c1):
        im = source.window(r0, r1, c0, c1)
        return [im.albedo, None if im.normals is None else check_normals(im.normals)], im.mask

    return _segment_superpixels(_feature_windows(read, (h, w), sigma_px, colour_weight, normal_weight), (h, w),
                                scale=scale, min_size=min_size, superpixel_px=float(superpixel_px), tile=tile)


#: A superpixel's initial internal difference, in standard deviations of its pixels' features:
#: the largest edge of the pixel graph's spanning tree inside a region is a few deviations.
SPREAD_FACTOR = 1.25
#: SLIC's blocks: at least this many f x f pixel blocks make one superpixel (:func:`_decimation`).
BLOCKS_PER_SUPERPIXEL = 16
#: SLIC's k-means iterations.
SLIC_ITERATIONS = 5


def _feature_windows(read, shape, sigma_px: float, colour_weight: float, normal_weight: float):
    """``window(r0, r1, c0, c1) -> (features, mask)``: the weighted, blurred colour+normal
    channels of a window, read with ``read(r0, r1, c0, c1) -> ([albedo, normals], mask)`` with a
    halo of 4 sigma + 2 px, so windows agree with a whole-image blur (exactly for sigma_px < 3,
    where the Gaussian is applied directly; the Gaussian is linear, so each 3-channel part is
    blurred by one contiguous OpenCV call and weighted into the stack)."""
    h, w = shape
    halo = int(np.ceil(4.0 * sigma_px)) + 2 if sigma_px > 0 else 0

    def window(r0, r1, c0, c1):
        ra, rb, ca, cb = max(0, r0 - halo), min(h, r1 + halo), max(0, c0 - halo), min(w, c1 + halo)
        (albedo, normals), mask = read(ra, rb, ca, cb)
        parts = [(np.asarray(v, np.float32), np.float32(wt)) for v, wt in ((albedo, colour_weight),
                                                                           (normals, normal_weight))
                 if v is not None and wt > 0]
        feats = np.empty((r1 - r0, c1 - c0, 3 * len(parts)), np.float32)
        core = (slice(r0 - ra, r1 - ra), slice(c0 - ca, c1 - ca))
        for i, (values, weight) in enumerate(parts):
            if sigma_px > 0:
                values = gaussian_blur(values, float(sigma_px))
            np.multiply(values[core], weight, out=feats[..., 3 * i:3 * i + 3])
        return feats, np.asarray(mask, bool)[core]

    return window


def _decimation(superpixel_px: float) -> int:
    """Side f of the pixel blocks SLIC works on: the largest with >= :data:`BLOCKS_PER_SUPERPIXEL`
    blocks in a superpixel (64-px superpixels: 2 x 2 blocks)."""
    return max(1, int(np.sqrt(superpixel_px / BLOCKS_PER_SUPERPIXEL)))


def _block_sums(values: np.ndarray, f: int) -> np.ndarray:
    """Sums of ``values`` (H, W[, C]) over f x f blocks, the last block row and column partial:
    the rows of each block first (whole contiguous rows added), then the columns."""
    h, w = values.shape[:2]
    hs, ws = -(-h // f), -(-w // f)
    rows = np.zeros((hs,) + values.shape[1:], np.float32)
    for dy in range(f):
        part = values[dy::f]
        rows[:part.shape[0]] += part
    out = np.zeros((hs, ws) + values.shape[2:], np.float32)
    for dx in range(f):
        part = rows[:, dx::f]
        out[:, :part.shape[1]] += part
    return out


def _segment_superpixels(window, shape, *, scale: float, min_size: int, superpixel_px: float,
                         tile: int = 2048) -> np.ndarray:
    """SLIC superpixels (Achanta et al. 2012; in tiles of ``tile`` px, each read by
    ``window(r0, r1, c0, c1) -> (features, mask)``) merged by Felzenszwalb-Huttenlocher's
    criterion on their adjacency graph; labels by decreasing area, -1 outside the mask.

    SLIC runs on the means of f x f pixel blocks (:func:`_superpixel_tile`), f^2 times fewer
    pixels for the same superpixels, and the boundaries between unlike superpixels are then
    placed at full resolution. Memory: the (H, W) int32 label map, one tile's work and a few
    numbers per superpixel."""
    h, w = shape
    f = _decimation(superpixel_px)
    tile = max(f, tile - tile % f)   # tiles start on the block grid
    tau = float(scale) / 255.0
    sp = np.full((h, w), -1, np.int32)
    nxt = 0
    areas, sums, sqs, pairs = [], [], [], []
    for r0 in range(0, h, tile):
        for c0 in range(0, w, tile):
            r1, c1 = min(h, r0 + tile), min(w, c0 + tile)
            feats, m = window(r0, r1, c0, c1)
            if not m.any():
                continue
            local, area, s1, s2, codes = _superpixel_tile(feats, m, f, max(1, int(m.size / superpixel_px)), tau)
            del feats
            sp[r0:r1, c0:c1] = np.where(local >= 0, local + nxt, -1)
            areas.append(area)
            sums.append(s1)
            sqs.append(s2)
            pairs.append(codes + ((nxt << 32) | nxt))
            nxt += area.size
    k = nxt
    if k == 0:
        return sp
    # adjacency across the tiles' seams, on the rows and columns either side
    seams = [(sp[r - 1], sp[r]) for r in range(tile, h, tile)] + [(sp[:, c - 1], sp[:, c]) for c in range(tile, w, tile)]
    for a, b in seams:
        d = (a != b) & (a >= 0) & (b >= 0)
        pairs.append(_pair_codes(a[d], b[d]))
    codes = np.unique(np.concatenate(pairs))
    ea, eb = codes >> 32, codes & 0xFFFFFFFF
    area, means, spread = _superpixel_stats(np.concatenate(areas), np.concatenate(sums), np.concatenate(sqs))
    weight = np.sqrt(((means[ea] - means[eb]) ** 2).sum(axis=1))
    order = np.argsort(weight, kind="stable")
    ea, eb = ea[order], eb[order]
    root = _felzenszwalb_merge(ea, eb, weight[order], area, spread, tau, int(min_size))
    # number the segments by decreasing area on the superpixels (a superpixel whose pixels all
    # went to its neighbours has none left), then one gather over the image
    seg = _relabel_by_area(root, area > 0, weights=area)
    for r0 in range(0, h, tile):   # in place, strip by strip
        strip = sp[r0:r0 + tile]
        strip[...] = np.where(strip >= 0, seg[np.maximum(strip, 0)], -1)
    return sp


def _superpixel_stats(area, sums, sqs):
    """(area, mean features, initial internal difference) of superpixels from their pixel count
    and the sums of their features and squared features."""
    n = np.maximum(area, 1)[:, None]
    means = sums / n
    var = np.maximum(sqs / n - means ** 2, 0.0)
    # a superpixel starts with the internal difference of its own pixels (their spread), as the
    # pixel graph's Int(C) would have grown while building it
    return area, means, SPREAD_FACTOR * np.sqrt(var.sum(axis=1))


def _superpixel_tile(feats: np.ndarray, m: np.ndarray, f: int, n_segments: int, tau: float):
    """SLIC superpixels of one tile, found on the means of f x f pixel blocks, with the boundaries
    between unlike superpixels placed per pixel.

    Parameters
    ----------
    feats : (h, w, C) float32
        The tile's weighted colour+normal features.
    m : (h, w) bool
        The mask.
    f : int
        Block side (:func:`_decimation`).
    n_segments : int
        SLIC's number of superpixels (as many as at full resolution).
    tau : float
        Felzenszwalb-Huttenlocher's ``k`` in feature units (``scale / 255``).

    Returns
    -------
    labels : (h, w) int32
        Superpixels 0..n-1 inside the mask, -1 outside.
    area, sums, sqs : (n,), (n, C), (n, C) float64
        Each superpixel's pixel count inside the mask and the sums of its pixels' features and
        squared features (at full resolution).
    codes : (E,) int64
        ``a << 32 | b`` (a < b) of the 4-adjacent superpixel pairs.

    Notes
    -----
    SLIC (Achanta et al. 2012, scikit-image's compiled implementation) clusters the block means,
    f^2 times fewer pixels than the tile for the same superpixels. A block that straddles a step
    has a mean of neither side, and SLIC makes superpixels of such blocks, whole blocks wide,
    which the merging would keep as segments of their own. So every pixel of a block on a
    boundary between two superpixels that Felzenszwalb-Huttenlocher's criterion would not join
    (weight > min(Int + tau / |C|) of the two, each on its own, Int its spread) takes the
    superpixel, among its own and those f px away in the 8 directions, whose mean is nearest its
    features: a superpixel of a ramp's blocks keeps the ramp's middle only, as at full
    resolution, and the merging's minimum size removes it. The statistics and adjacency are those
    of the pixels after this step.
    """
    from skimage.segmentation import slic

    h, w = m.shape
    if m.all():
        count = np.outer(np.minimum(f, h - f * np.arange(-(-h // f))),   # pixels per block (the last
                         np.minimum(f, w - f * np.arange(-(-w // f)))).astype(np.float32)   # ones may be partial)
        inside = _block_sums(feats, f)
        sq = _block_sums(np.square(feats), f)
    else:
        mf = m.astype(np.float32)
        count = _block_sums(mf, f)
        masked = feats * mf[..., None]
        inside = _block_sums(masked, f)
        masked *= feats
        sq = _block_sums(masked, f)
        del masked
    valid = count > 0
    # the blocks' mean features inside the mask (0 in the blocks outside it)
    lab = slic(inside / np.maximum(count, 1)[..., None], n_segments=n_segments, compactness=0.05, sigma=0,
               channel_axis=-1, start_label=0, max_num_iter=SLIC_ITERATIONS, enforce_connectivity=True)
    # a superpixel that straddles the mask border is cut by it; the labels that occur inside the
    # mask are numbered densely (a bincount and a cumulative sum: linear, no sort)
    present = np.bincount(lab[valid], minlength=int(lab.max()) + 1) > 0
    n = int(present.sum())
    local = np.where(valid, np.cumsum(present)[lab] - 1, -1).astype(np.int32)
    flat = (local + 1).ravel()   # bin 0: outside the mask, dropped
    area = np.bincount(flat, weights=count.ravel(), minlength=n + 1)[1:]
    s1 = np.stack([np.bincount(flat, weights=inside[..., c].ravel(), minlength=n + 1)[1:]
                   for c in range(inside.shape[2])], axis=1)
    s2 = np.stack([np.bincount(flat, weights=sq[..., c].ravel(), minlength=n + 1)[1:]
                   for c in range(sq.shape[2])], axis=1)
    # the 4-adjacent block pairs of different superpixels, a code per facing pair
    sides = []
    for a, b in ((local[:, :-1], local[:, 1:]), (local[:-1], local[1:])):
        d = (a != b) & (a >= 0) & (b >= 0)
        sides.append((d, _pair_codes(a[d], b[d], repeats=True)))
    codes = np.unique(np.concatenate([_drop_repeats(c) for _, c in sides]))
    labels = np.where(m, local.repeat(f, axis=0)[:h].repeat(f, axis=1)[:, :w], -1) if f > 1 else local
    if f == 1 or codes.size == 0:
        return labels, area, s1, s2, codes
    # the blocks on a boundary between unlike superpixels, by the criterion the merging applies
    _, means, spread = _superpixel_stats(area, s1, s2)
    ea, eb = codes >> 32, codes & 0xFFFFFFFF
    limit = spread + tau / np.maximum(area, 1)
    unlike = np.sqrt(((means[ea] - means[eb]) ** 2).sum(axis=1)) > np.minimum(limit[ea], limit[eb])
    marked = np.zeros(local.shape, bool)
    hits = []
    for (d, c), (ma, mb) in zip(sides, ((marked[:, :-1], marked[:, 1:]), (marked[:-1], marked[1:]))):
        hit = np.zeros(d.shape, bool)
        hit[d] = unlike[np.searchsorted(codes, c)]
        ma |= hit
        mb |= hit
        hits.append(hit)
    # their pixels take the nearest superpixel among their own and those f px away
    ys, xs = np.nonzero(marked.repeat(f, axis=0)[:h].repeat(f, axis=1)[:, :w] & (labels >= 0))
    x = feats[ys, xs]
    means = means.astype(np.float32)
    own = labels[ys, xs]
    best, best_d = own, ((means[own] - x) ** 2).sum(axis=1)
    for dy in (-f, 0, f):
        for dx in (-f, 0, f):
            if dy == dx == 0:
                continue
            cand = labels[np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)]
            dist = ((means[np.maximum(cand, 0)] - x) ** 2).sum(axis=1)
            better = (dist < best_d) & (cand >= 0)
            best = np.where(better, cand, best)
            best_d = np.where(better, dist, best_d)
    moved = best != own
    x, own, best = x[moved].astype(np.float64), own[moved], best[moved]
    labels[ys[moved], xs[moved]] = best
    area = area - np.bincount(own, minlength=n) + np.bincount(best, minlength=n)
    for c in range(x.shape[1]):
        v = x[:, c]
        s1[:, c] += np.bincount(best, weights=v, minlength=n) - np.bincount(own, weights=v, minlength=n)
        v = v * v
        s2[:, c] += np.bincount(best, weights=v, minlength=n) - np.bincount(own, weights=v, minlength=n)
    # adjacency: the block pairs away from the marked blocks, and the pixel pairs at and beside them
    pairs = []
    for (d, c), (ma, mb) in zip(sides, ((marked[:, :-1], marked[:, 1:]), (marked[:-1], marked[1:]))):
        pairs.append(_drop_repeats(c[~(ma | mb)[d]]))
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        y2, x2 = ys + dy, xs + dx
        on = (y2 >= 0) & (y2 < h) & (x2 >= 0) & (x2 < w)
        a, b = labels[ys[on], xs[on]], labels[y2[on], x2[on]]
        d = (a != b) & (a >= 0) & (b >= 0)
        pairs.append(_pair_codes(a[d], b[d]))
    return labels, area, s1, s2, np.unique(np.concatenate(pairs))


def _pair_codes(a: np.ndarray, b: np.ndarray, repeats: bool = False) -> np.ndarray:
    """Codes ``min << 32 | max`` of facing labels ``a``, ``b`` (1-d, int32): one per pixel pair
    (``repeats``) or with a pair repeating the one before dropped (:func:`_drop_repeats`)."""
    a, b = a.astype(np.int64), b.astype(np.int64)
    codes = (np.minimum(a, b) << 32) | np.maximum(a, b)
    return codes if repeats else _drop_repeats(codes)


def _drop_repeats(codes: np.ndarray) -> np.ndarray:
    """``codes`` without the elements equal to the one before: a boundary is crossed by the same
    pair pixel after pixel, and this linear pass spares the sort-based unique most of them."""
    return codes[np.concatenate(([True], codes[1:] != codes[:-1]))] if codes.size > 1 else codes


def _felzenszwalb_merge(ea: np.ndarray, eb: np.ndarray, weight: np.ndarray, area: np.ndarray,
                        spread: np.ndarray, tau: float, min_size: int) -> np.ndarray:
    """Felzenszwalb-Huttenlocher merging of a region graph: edges ``(ea[i], eb[i])`` in increasing
    ``weight`` join two components when ``weight <= min(Int(C) + tau / |C|)`` over both (Int
    starting at ``spread``, |C| at ``area``), then components under ``min_size`` join a neighbour;
    returns each node's component root.

    The merge is sequential (each decision depends on the earlier ones), so it runs as a Python
    loop over the edges; what is not sequential is done in numpy: the minimum-size pass visits only
    the edges with an end in a component still under ``min_size`` after the first pass (an edge
    between two components of at least ``min_size`` can never join them, and components only grow),
    and the roots are found by pointer jumping over the whole parent array.

    References
    ----------
    P. F. Felzenszwalb, D. P. Huttenlocher, "Efficient graph-based image segmentation", IJCV 59(2),
    2004, §4 (the criterion) and §5 (the minimum size).
    """
    k = area.shape[0]
    parent = list(range(k))
    size = area.tolist()
    thresh = (spread + tau / np.maximum(area, 1e-12)).tolist()   # Int(C) + tau / |C|, per root
    internal = spread.tolist()
    for a, b, wt in zip(ea.tolist(), eb.tolist(), weight.tolist()):
        # find with path halving, inlined (a function call per lookup costs as much as the rest)
        while parent[a] != a:
            parent[a] = a = parent[parent[a]]
        while parent[b] != b:
            parent[b] = b = parent[parent[b]]
        if a != b and wt <= thresh[a] and wt <= thresh[b]:
            parent[b] = a
            size[a] += size[b]
            internal[a] = i = max(wt, internal[a], internal[b])
            thresh[a] = i + tau / size[a]
    root = _roots(np.asarray(parent, np.int64))
    small = np.asarray(size)[root] < min_size
    keep = small[ea] | small[eb]
    if keep.any():
        parent = root.tolist()   # already flat: every node points at its root
        for a, b in zip(ea[keep].tolist(), eb[keep].tolist()):
            while parent[a] != a:
                parent[a] = a = parent[parent[a]]
            while parent[b] != b:
                parent[b] = b = parent[parent[b]]
            if a != b and (size[a] < min_size or size[b] < min_size):
                parent[b] = a
                size[a] += size[b]
        root = _roots(np.asarray(parent, np.int64))
    return root


def _roots(parent: np.ndarray) -> np.ndarray:
    """The root of every node of a union-find forest, by pointer jumping (log depth passes)."""
    while True:
        up = parent[parent]
        if np.array_equal(up, parent):
            return parent
        parent = up


def _segment_downsampled(albedo, normals, mask, shape, *, max_megapixels, **kw):
    import cv2

    h, w = shape
    f = int(np.ceil(np.sqrt(h * w / (max_megapixels * 1e6))))
    size = (max(1, w // f), max(1, h // f))
    small = lambda a: None if a is None else cv2.resize(a, size, interpolation=cv2.INTER_AREA)  # noqa: E731
    n_small = small(normals)
    if n_small is not None:
        n_small /= np.maximum(np.linalg.norm(n_small, axis=2, keepdims=True), 1e-12)
    m_small = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    kw = dict(kw, sigma_px=kw["sigma_px"] / f, min_size=max(1, int(round(kw["min_size"] / f ** 2))))
    labels = segment_rgbn(small(albedo), n_small, mask=m_small, max_megapixels=None, **kw)
    up = cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)
    # the mask stays exact; mask pixels that fell on background in the small grid take the
    # nearest label, background pixels that fell on the fragment become -1
    up[~mask] = -1
    if ((up < 0) & mask).any():
        import scipy.ndimage as ndi

        idx = ndi.distance_transform_edt(up < 0, return_distances=False, return_indices=True)
        up = np.where(mask, up[idx[0], idx[1]], -1)
    return up.astype(np.int32)


def _relabel_by_area(labels: np.ndarray, mask: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Labels renumbered 0..K-1 by decreasing area (``weights``: the area of each element, default 1;
    ties by increasing old label), -1 outside ``mask``; a bincount, linear in the pixels."""
    lab = np.where(mask, labels, -1).astype(np.int64, copy=False)
    counts = np.bincount(lab.ravel() + 1, weights=None if weights is None else np.where(mask, weights, 0).ravel())[1:]
    present = np.bincount(lab.ravel() + 1, minlength=counts.size + 1)[1:] > 0
    ids = np.flatnonzero(present)
    order = ids[np.argsort(-counts[ids], kind="stable")]
    new_ids = np.full(counts.size + 1, -1, np.int32)
    new_ids[order + 1] = np.arange(order.size, dtype=np.int32)
    return new_ids[lab + 1]


def segment_means(values: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Replace every pixel of ``values`` (H, W[, C]) by the mean over its segment (label -1 kept)."""
    values = np.asarray(values, dtype=np.float32)
    if values.shape[:2] != labels.shape:
        raise ValueError(f"values shape {values.shape[:2]} differs from labels shape {labels.shape}")
    flat = values.reshape(labels.size, -1)
    lab = labels.ravel()
    inside = lab >= 0
    k = int(lab.max(initial=-1)) + 1
    out = flat.copy()
    if k:
        counts = np.bincount(lab[inside], minlength=k).astype(np.float64)
        for c in range(flat.shape[1]):
            sums = np.bincount(lab[inside], weights=flat[inside, c], minlength=k)
            out[inside, c] = (sums / np.maximum(counts, 1))[lab[inside]]
    return out.reshape(values.shape)
