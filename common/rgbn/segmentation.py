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
        (scikit-image's compiled implementation, on the weighted colour+normal channels, in
        2048-px windows blurred with a halo; :func:`segment_source` reads them one at a time from
        an image larger than memory) cuts the image into regions of about this
        many pixels, and Felzenszwalb-Huttenlocher's merging runs on their adjacency graph with
        the distance between region means as the edge weight and region areas in pixels.
        "auto": 64-pixel superpixels above 0.25 Mpx, the pixel graph below. None: always the
        pixel graph (about 5 CPU s/Mpx with six channels, and ~500 bytes a pixel).

    Returns
    -------
    (H, W) int32
        Labels 0..K-1 ordered by decreasing area (0 = largest segment); -1 outside the mask.

    References
    ----------
    Toler-Franklin 2011, §7.2.4; P. Felzenszwalb, D. Huttenlocher, "Efficient graph-based image
    segmentation", IJCV 59(2), 2004.

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
    and cut into SLIC superpixels one ``tile`` x ``tile`` window at a time, and only the (H, W)
    int32 label map (4 bytes a pixel) and a few numbers per superpixel are kept for the merging.
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


def _segment_superpixels(window, shape, *, scale: float, min_size: int, superpixel_px: float,
                         tile: int = 2048) -> np.ndarray:
    """SLIC superpixels (in tiles of ``tile`` px, each read by ``window(r0, r1, c0, c1) ->
    (features, mask)``) merged by Felzenszwalb-Huttenlocher's criterion on their adjacency graph;
    labels by decreasing area, -1 outside the mask. Memory: the (H, W) int32 label map, one tile's
    work and a few numbers per superpixel."""
    from skimage.segmentation import slic

    h, w = shape
    sp = np.full((h, w), -1, np.int32)
    nxt = 0
    areas, sums, sqs = [], [], []
    for r0 in range(0, h, tile):
        for c0 in range(0, w, tile):
            r1, c1 = min(h, r0 + tile), min(w, c0 + tile)
            feats, m = window(r0, r1, c0, c1)
            if not m.any():
                continue
            n_seg = max(1, int(m.size / superpixel_px))
            lab = slic(feats, n_segments=n_seg, compactness=0.05, sigma=0, channel_axis=-1, start_label=0,
                       max_num_iter=5, enforce_connectivity=True)
            # a superpixel that straddles the mask border is cut by it; the tile's labels that
            # occur inside the mask are numbered densely (a bincount and a cumulative sum: linear,
            # no sort), after the previous tiles'
            present = np.bincount(lab[m] if not m.all() else lab.ravel(), minlength=int(lab.max()) + 1) > 0
            dense = np.cumsum(present) - 1
            n = int(present.sum())
            local = np.where(m, dense[lab], -1)
            sp[r0:r1, c0:c1] = np.where(m, local + nxt, -1)
            # per-superpixel sums over bin local + 1 (bin 0: outside the mask, dropped)
            flat = (local + 1).ravel()
            areas.append(np.bincount(flat, minlength=n + 1)[1:].astype(np.float64))
            s1, s2 = [], []
            for c in range(feats.shape[2]):
                v = feats[..., c].ravel().astype(np.float64)
                s1.append(np.bincount(flat, weights=v, minlength=n + 1)[1:])
                v *= v
                s2.append(np.bincount(flat, weights=v, minlength=n + 1)[1:])
            sums.append(np.stack(s1, axis=1))
            sqs.append(np.stack(s2, axis=1))
            nxt += n
    k = nxt
    if k == 0:
        return sp
    area = np.concatenate(areas)
    sums, sq = np.concatenate(sums), np.concatenate(sqs)
    means = sums / np.maximum(area, 1)[:, None]
    var = np.maximum(sq / np.maximum(area, 1)[:, None] - means ** 2, 0.0)
    # a superpixel starts with the internal difference of its own pixels (their spread), as the
    # pixel graph's Int(C) would have grown while building it
    spread = SPREAD_FACTOR * np.sqrt(var.sum(axis=1))
    # adjacency of superpixels (4-connected), in strips of rows so temporaries stay small
    pairs = []
    for r0 in range(0, h, tile):
        strip = sp[r0:min(h, r0 + tile + 1)]
        for a, b in ((strip[:tile, :-1], strip[:tile, 1:]), (strip[:-1], strip[1:])):
            d = (a != b) & (a >= 0) & (b >= 0)
            a, b = a[d].astype(np.int64), b[d].astype(np.int64)
            codes = np.minimum(a, b) * k + np.maximum(a, b)
            # a boundary is crossed by the same pair pixel after pixel: drop those repeats
            # (linear) before the sort-based unique sees the codes
            if codes.size > 1:
                codes = codes[np.concatenate(([True], codes[1:] != codes[:-1]))]
            pairs.append(np.unique(codes))
    codes = np.unique(np.concatenate(pairs)) if pairs else np.zeros(0, np.int64)
    ea, eb = codes // k, codes % k
    weight = np.sqrt(((means[ea] - means[eb]) ** 2).sum(axis=1))
    order = np.argsort(weight, kind="stable")
    ea, eb = ea[order], eb[order]
    root = _felzenszwalb_merge(ea, eb, weight[order], area, spread, float(scale) / 255.0, int(min_size))
    # number the segments by decreasing area on the superpixels, then one gather over the image
    seg = _relabel_by_area(root, np.ones(k, bool), weights=area)
    for r0 in range(0, h, tile):   # in place, strip by strip
        strip = sp[r0:r0 + tile]
        strip[...] = np.where(strip >= 0, seg[np.maximum(strip, 0)], -1)
    return sp


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
