"""Shading styles computed from the normals (§7.3): Lambertian and raking light, toon shading
with quantized colour, Gooch warm/cool, exaggerated shading, and (multiscale) mean curvature
shading.

Every function takes arrays (normals x right, y up, z to viewer) and returns display values in
[0, 1]; :mod:`common.render.recipes` turns them into layers.
"""

from __future__ import annotations

import numpy as np

from common.render._util import as_light, check_dpi, dot_light, scale_colour, smoothstep
from common.render.enhance import Coarse
from common.rgbn._filters import _blur_direct, check_mask, check_normals, gaussian_reach
from common.rgbn.curvature import mean_curvature
from common.rgbn.smoothing import copy_where, strips, unit_rows, weighted_stack


def lambertian(normals: np.ndarray, light=(135.0, 45.0), *, albedo: np.ndarray | None = None,
               ambient: float = 0.0) -> np.ndarray:
    """Lambertian shading ``albedo * (ambient + (1 - ambient) * max(0, n . l))``.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    light : 3-vector or (azimuth_deg, elevation_deg)
        Light direction; a raking light has a low elevation (5-20 degrees) and shows relief that a
        photograph hides (§7.3.1).
    albedo : (H, W, 3) float, optional
        Display colour; None gives grey shading (H, W).
    ambient : float
        Fraction of light that reaches every pixel, in [0, 1].

    Returns
    -------
    (H, W) or (H, W, 3) float32 in [0, 1]

    References
    ----------
    Toler-Franklin 2011, §7.3.1.

    Examples
    --------
    >>> n = np.zeros((2, 2, 3), np.float32); n[..., 2] = 1
    >>> float(lambertian(n, (0.0, 30.0))[0, 0])
    0.5
    """
    normals = check_normals(normals)
    return lambertian_of_cosine(dot_light(normals, as_light(light)), albedo=albedo, ambient=ambient)


def lambertian_of_cosine(cosine: np.ndarray, *, albedo: np.ndarray | None = None,
                         ambient: float = 0.0) -> np.ndarray:
    """:func:`lambertian` of the cosine ``n . l`` per pixel ((H, W) float), which a caller may have
    computed strip by strip or under a per-pixel light."""
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient must be in [0, 1], got {ambient}")
    shade = np.maximum(np.asarray(cosine, np.float32), np.float32(0.0))
    shade *= np.float32(1.0 - ambient)
    shade += np.float32(ambient)
    if albedo is None:
        return shade
    return scale_colour(_check_colour(albedo, shade.shape), shade)


def toon(normals: np.ndarray, light=(135.0, 45.0), *, levels: int = 3, softness: float = 0.02,
         dark: float = 0.35, colours: np.ndarray | None = None) -> np.ndarray:
    """Toon (cel) shading: ``n . l`` cut into ``levels`` bands with smooth steps (§7.3.2).

    Band boundaries are the isophotes ``n . l = j / levels`` (j = 1..levels-1) of the clamped
    Lambertian term; each boundary is a smoothstep of half-width ``softness`` centred on its
    isophote, so the tone is exactly half-way between two bands on the isophote itself.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    light : 3-vector or (azimuth_deg, elevation_deg)
        Light direction.
    levels : int
        Number of tone bands (>= 2).
    softness : float
        Half-width of each step in units of ``n . l`` (0 = hard steps).
    dark : float
        Brightness of the darkest band (the lightest is 1).
    colours : (H, W, 3) float, optional
        Flat colours to shade, e.g. :func:`quantize_colours` of the albedo; None gives grey.

    Returns
    -------
    (H, W) or (H, W, 3) float32 in [0, 1]

    References
    ----------
    Toler-Franklin 2011, §7.3.2; Lake et al., "Stylized rendering techniques for scalable
    real-time 3D animation", NPAR 2000.
    """
    normals = check_normals(normals)
    return toon_of_cosine(dot_light(normals, as_light(light)), levels=levels, softness=softness, dark=dark,
                          colours=colours)


def toon_of_cosine(cosine: np.ndarray, *, levels: int = 3, softness: float = 0.02, dark: float = 0.35,
                   colours: np.ndarray | None = None) -> np.ndarray:
    """:func:`toon` of the cosine ``n . l`` per pixel ((H, W) float)."""
    if int(levels) != levels or levels < 2:
        raise ValueError(f"levels must be an integer >= 2, got {levels}")
    if softness < 0:
        raise ValueError(f"softness must be >= 0, got {softness}")
    if not 0.0 <= dark <= 1.0:
        raise ValueError(f"dark must be in [0, 1], got {dark}")
    cosine = np.asarray(cosine, np.float32)
    colours = None if colours is None else _check_colour(colours, cosine.shape)
    shade = np.empty(cosine.shape, np.float32)
    out = None if colours is None else np.empty(cosine.shape + (3,), np.float32)
    for r0, r1, _, _ in strips(cosine.shape, 0):   # per pixel: a strip of rows at a time
        s = np.maximum(cosine[r0:r1], np.float32(0.0))
        tone = np.zeros_like(s)
        for j in range(1, int(levels)):
            t = j / levels
            tone += smoothstep(t - softness, t + softness, s)
        tone *= np.float32((1.0 - dark) / (levels - 1))
        tone += np.float32(dark)
        shade[r0:r1] = tone
        if colours is not None:
            scale_colour(colours[r0:r1], tone, out=out[r0:r1])
    return shade if colours is None else out


def quantize_colours(colours: np.ndarray, n_colours: int = 6, *, mask: np.ndarray | None = None,
                     sample: int = 20000, seed: int = 0) -> np.ndarray:
    """Replace each colour by its k-means cluster centre (the flat colours of toon shading, §7.3.2).

    Clusters are fitted on at most ``sample`` random mask pixels (deterministic for a ``seed``),
    then every pixel takes its nearest centre. Pixels outside the mask are returned unchanged.
    """
    colours = np.asarray(colours, dtype=np.float32)
    if colours.ndim != 3 or colours.shape[2] != 3:
        raise ValueError(f"colours must be (H, W, 3), got shape {colours.shape}")
    return nearest_colours(colours, kmeans_palette(colours, n_colours, mask=mask, sample=sample, seed=seed),
                           mask=mask)


def kmeans_palette(colours: np.ndarray, n_colours: int = 6, *, mask: np.ndarray | None = None,
                   sample: int = 20000, seed: int = 0) -> np.ndarray:
    """The k-means palette (k, 3) of an (H, W, 3) colour image, fitted on at most ``sample`` mask
    pixels (deterministic for a ``seed``); an all-background image gives an empty palette."""
    import cv2

    colours = np.asarray(colours, dtype=np.float32)
    if colours.ndim != 3 or colours.shape[2] != 3:
        raise ValueError(f"colours must be (H, W, 3), got shape {colours.shape}")
    if int(n_colours) != n_colours or n_colours < 1:
        raise ValueError(f"n_colours must be an integer >= 1, got {n_colours}")
    mask = check_mask(mask, colours.shape[:2])
    at = palette_pixels(mask, sample=sample, seed=seed)   # only the sample's colours are gathered
    if at.size == 0:
        return np.zeros((0, 3), np.float32)
    fit = colours.reshape(-1, 3)[at]
    k = int(min(n_colours, len(np.unique(fit, axis=0))))
    # OpenCV's k-means (k-means++ seeding, 3 attempts): fast and single-threaded, so it behaves on
    # a loaded machine; its RNG is seeded for a deterministic palette
    cv2.setRNGSeed(int(seed))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-5)
    _, _, centres = cv2.kmeans(np.ascontiguousarray(fit), k, None, criteria, 3, cv2.KMEANS_PP_CENTERS)
    return centres.astype(np.float32)


def palette_pixels(mask: np.ndarray, *, sample: int = 20000, seed: int = 0) -> np.ndarray:
    """The flat positions of the pixels :func:`kmeans_palette` fits its palette on, in the order
    it takes them: every mask pixel, or ``sample`` of them drawn at random (deterministic for a
    ``seed``). A caller that has the colours of only some pixels (a window of the image) gathers
    the colours of these and fits them (``mask=None``) to the same palette."""
    at = np.flatnonzero(np.asarray(mask, bool))
    if at.size <= sample:
        return at
    return at[np.random.default_rng(seed).choice(at.size, sample, replace=False)]


def nearest_colours(colours: np.ndarray, centres: np.ndarray, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Each mask pixel of an (H, W, 3) image replaced by the nearest of ``centres`` (k, 3)."""
    colours = np.asarray(colours, dtype=np.float32)
    centres = np.asarray(centres, np.float32).reshape(-1, 3)
    mask = check_mask(mask, colours.shape[:2])
    out = colours.copy()
    if centres.shape[0] == 0:
        return out
    import cv2

    # strips of ~1 Mpx rows, the channels as contiguous planes, one centre at a time (squared
    # distance channel by channel, the first of equally near centres kept, as argmin); the chosen
    # centre's channels are looked up per plane: no per-pixel gathers, bounded memory
    for r0, r1, _, _ in strips(colours.shape, 0):
        planes = cv2.split(np.ascontiguousarray(colours[r0:r1]))
        best = idx = None
        d, e = np.empty_like(planes[0]), np.empty_like(planes[0])
        for j, centre in enumerate(centres):
            np.subtract(planes[0], centre[0], out=d)
            d *= d
            for ch in (1, 2):
                np.subtract(planes[ch], centre[ch], out=e)
                e *= e
                d += e
            if best is None:
                best, idx, d = d, np.zeros(d.shape, np.intp), np.empty_like(d)
            else:
                closer = d < best
                np.copyto(best, d, where=closer)
                idx[closer] = j
        chosen = cv2.merge([np.take(centres[:, ch], idx) for ch in range(3)])
        copy_where(out[r0:r1], chosen, mask[r0:r1])
    return out


def gooch(normals: np.ndarray, light=(135.0, 45.0), *, albedo: np.ndarray | None = None,
          blue: float = 0.4, yellow: float = 0.4, alpha: float = 0.2, beta: float = 0.6) -> np.ndarray:
    """Gooch warm/cool shading: hue, not only brightness, shows orientation.

    ``c = t * k_warm + (1 - t) * k_cool`` with ``t = (1 + n . l) / 2``,
    ``k_cool = (0, 0, blue) + alpha * kd`` and ``k_warm = (yellow, yellow, 0) + beta * kd``.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    light : 3-vector or (azimuth_deg, elevation_deg)
        Light direction.
    albedo : (H, W, 3) float, optional
        Diffuse colour kd (display values); None uses a neutral 0.75 grey.
    blue, yellow, alpha, beta : float
        The paper's b, y, alpha, beta.

    Returns
    -------
    (H, W, 3) float32 in [0, 1]

    References
    ----------
    A. Gooch, B. Gooch, P. Shirley, E. Cohen, "A non-photorealistic lighting model for automatic
    technical illustration", SIGGRAPH 1998, §4.2; Toler-Franklin 2011, §7.3.
    """
    normals = check_normals(normals)
    return gooch_of_cosine(dot_light(normals, as_light(light)), albedo=albedo, blue=blue, yellow=yellow,
                           alpha=alpha, beta=beta)


def gooch_of_cosine(cosine: np.ndarray, *, albedo: np.ndarray | None = None, blue: float = 0.4,
                    yellow: float = 0.4, alpha: float = 0.2, beta: float = 0.6) -> np.ndarray:
    """:func:`gooch` of the cosine ``n . l`` per pixel ((H, W) float)."""
    import cv2

    cosine = np.asarray(cosine, np.float32)
    kd = None if albedo is None else _check_colour(albedo, cosine.shape)
    # t k_warm + (1 - t) k_cool = kd (alpha + (beta - alpha) t) + (yellow t, yellow t, blue (1 - t)):
    # a colour times a plane plus three planes, which OpenCV computes on interleaved channels
    # (numpy's broadcast over a last axis of 3 is slow; cv2.transform of t, 3x slower than the
    # planes and their merge), a strip of rows at a time
    out = np.empty(cosine.shape + (3,), np.float32)
    for r0, r1, _, _ in strips(cosine.shape, 0):
        t = cosine[r0:r1] + np.float32(1.0)
        t *= np.float32(0.5)
        a = t * np.float32(beta - alpha)
        a += np.float32(alpha)
        o = out[r0:r1]
        if kd is None:
            a *= np.float32(0.75)
            cv2.merge([a, a, a], dst=o)
        else:
            cv2.multiply(np.ascontiguousarray(kd[r0:r1]), cv2.merge([a, a, a]), dst=o)
        warm = t * np.float32(yellow)
        t *= np.float32(-blue)
        t += np.float32(blue)
        cv2.add(o, cv2.merge([warm, warm, t]), dst=o)
        np.clip(o, 0.0, 1.0, out=o)
    return out


def exaggerated_shading(normals: np.ndarray, light=(135.0, 45.0), *, mask: np.ndarray | None = None,
                        scales: int = 8, sigma0_px: float = 1.0, sigma_ratio: float = 2.0,
                        contrast: float = 10.0, detail: float = 0.5, base_weight: float = 0.3,
                        foreshortening: bool = True, origin=(0, 0), coarse: bool = True,
                        finest: np.ndarray | None = None) -> np.ndarray:
    """Exaggerated shading (Rusinkiewicz, Burns & DeCarlo 2006) of a normal map (§7.3.5).

    With normals ``n_i`` smoothed at ``sigma_i = sigma0 * ratio^i`` (i = 0..scales, the last one
    being the base), the light at scale i is the global light projected into the tangent plane of
    the next-coarser normal, ``l_{i+1} = normalize(l - (l . n_{i+1}) n_{i+1})`` — always grazing
    with respect to the overall shape, so every bump at every scale is lit from the side. Each
    scale contributes ``c_i = clamp(contrast * n_i . l_{i+1}, -1, 1)``; the base adds ordinary
    clamped lighting ``c_b = clamp(contrast * n_b . l)``. The result is ::

        0.5 + 0.5 * (sum_i k_i c_i + k_b c_b) / (sum_i k_i + k_b),   k_i = sigma_i^(-detail)

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    light : 3-vector or (azimuth_deg, elevation_deg)
        Global light direction.
    mask : (H, W) bool, optional
        Pixels carrying normals (smoothing ignores the rest).
    scales : int
        Number of detail scales (the paper's examples use 6-10).
    sigma0_px, sigma_ratio : float
        Finest smoothing (pixels) and the factor between consecutive scales.
    contrast : float
        The paper's ``a``: high values give toon-like, saturated shading.
    detail : float
        Exponent of the per-scale weights ``k_i = sigma_i^-detail``: 0 weights all scales equally,
        1 strongly favours fine detail.
    base_weight : float
        Weight ``k_b`` of the base (coarsest) lighting relative to the normalized detail weights.
    foreshortening : bool
        Use the 1/nz-corrected smoothing of §7.2.1.
    origin : (int, int)
        Row and column of this window in the whole image (tiles): the coarse grids are aligned to
        the whole image's, so overlapping tiles draw the same values.
    coarse : bool
        Draw the pairs of levels whose finer sigma is >= 4 px on grids 2, 4, … times coarser
        (default; within 1/255 of the full-resolution result at a half to a third of its cost).
        False computes every level at full resolution (the reference).
    finest : (H, W, 3) float, optional
        The normals already smoothed at ``sigma0_px`` (:func:`common.rgbn.smoothing.smooth_normals`
        with the same mask and ``foreshortening``): a recipe computes them once for all its layers.
        None computes them here.

    Returns
    -------
    (H, W) float32 in [0, 1]

    References
    ----------
    S. Rusinkiewicz, M. Burns, D. DeCarlo, "Exaggerated shading for depicting shape and detail",
    ACM TOG 25(3) (SIGGRAPH 2006), §3; Toler-Franklin 2011, §7.3.5.

    Examples
    --------
    >>> n = np.zeros((32, 32, 3), np.float32); n[..., 2] = 1
    >>> float(exaggerated_shading(n, scales=3, base_weight=0.0).std())
    0.0
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if int(scales) != scales or scales < 1:
        raise ValueError(f"scales must be an integer >= 1, got {scales}")
    if not sigma0_px > 0:
        raise ValueError(f"sigma0_px must be > 0, got {sigma0_px}")
    if not sigma_ratio > 1:
        raise ValueError(f"sigma_ratio must be > 1, got {sigma_ratio}")
    if not contrast > 0:
        raise ValueError(f"contrast must be > 0, got {contrast}")
    if base_weight < 0:
        raise ValueError(f"base_weight must be >= 0, got {base_weight}")
    l = as_light(light)
    sigmas = [sigma0_px * sigma_ratio ** i for i in range(int(scales) + 1)]
    weights = np.array([s ** -detail for s in sigmas[:-1]], np.float64)
    weights /= weights.sum()
    a = np.float32(contrast)
    h, w = normals.shape[:2]
    if finest is not None and np.shape(finest) != normals.shape:
        raise ValueError(f"finest must be {normals.shape}, got {np.shape(finest)}")
    # a level of sigma >= 2 f px is smoothed on a grid f times coarser (f a power of two, the
    # grid aligned to the whole image's for tiles): a Gaussian of >= 2 grid steps leaves nothing
    # above the grid's Nyquist rate (its response there is exp(-pi^2 s^2 / 2) < 3e-9); a pair's
    # term is drawn on its finer level's grid and brought back by bilinear interpolation, within
    # 1/255 of the full-resolution result (test)
    grids = [_coarse_factor(s, h, w, coarse) for s in sigmas]
    n_full = grids.count(1)   # the finest levels (a prefix: sigma grows), drawn in row strips
    pyramid = _WeightedPyramid(normals, mask, foreshortening, origin) if n_full < len(sigmas) else None
    acc: dict = {}
    prev = partner = None
    if n_full and pyramid is not None:
        # the first coarse level, partner of the last full-resolution one
        partner = pyramid.level(sigmas[n_full], grids[n_full])
        prev = (partner, grids[n_full])
    for k in range(n_full + 1 if n_full else 0, len(sigmas)):
        f = grids[k]
        n_k = pyramid.level(sigmas[k], f)
        if prev is not None:
            n_i, f_i = prev
            n_c = n_k if f == f_i else pyramid.resample(n_k, f, f_i)
            term = _exaggerated_term(n_i, n_c, l, a)
            term *= np.float32(weights[k - 1])
            if f_i in acc:
                acc[f_i] += term
            else:
                acc[f_i] = term
            del n_c, term
        prev = (n_k, f)
    if prev is not None and base_weight > 0:   # the base level is coarse (else drawn in the strips)
        n_b, f_b = prev
        term = np.float32(base_weight) * np.clip(a * dot_light(n_b, l), -1.0, 1.0)
        acc[f_b] = acc[f_b] + term if f_b in acc else term
        del n_b
    del prev
    scale = np.float32(0.5 / (1.0 + base_weight))
    terms = [Coarse(term, f, pyramid.offset(f)) for f, term in acc.items()]
    del acc
    if n_full:
        # the full-resolution levels in row strips, each strip adding the coarse grids' terms
        return _exaggerated_full(normals, mask, sigmas[:n_full], weights, l, a, foreshortening, finest,
                                 None if partner is None else Coarse(partner, grids[n_full],
                                                                      pyramid.offset(grids[n_full])),
                                 0.0 if partner is not None else base_weight, terms, scale)
    total = np.zeros((h, w), np.float32)
    for term in terms:
        total += term.full((h, w))
    total *= scale
    total += np.float32(0.5)
    return total


def _exaggerated_full(normals, mask, sigmas, weights, l, a, foreshortening, finest, partner, base_weight,
                      terms=(), scale=None):
    """The full-resolution part of :func:`exaggerated_shading`, row strip by row strip (each
    strip's levels, terms and their weighted sum made from the strip and a halo of the widest
    kernel's reach, so no temporary is of the image's size): the weighted terms of the pairs of
    ``sigmas`` (px), then of the last with ``partner`` (the next level on its coarse grid, a
    :class:`common.render.enhance.Coarse`, brought to the strip's rows by bilinear interpolation)
    or, without one, ``base_weight`` times the base lighting of the last; then the ``terms`` drawn
    on coarser grids (:class:`common.render.enhance.Coarse`, interpolated to the strip's rows, in
    their order) and, with ``scale``, the sum mapped to ``0.5 + scale * sum``. (H, W) float32.

    Only ``w n`` is blurred (:func:`common.rgbn.smoothing.weighted_stack` without its weight, a
    quarter less blurring): each term is made from one pixel's levels, so a level off the mask
    beyond its kernel's reach (where :func:`common.rgbn.smoothing.smooth_normals` keeps the input
    normal) is read only there, outside what is drawn; it is the zero vector here."""
    h, w = normals.shape[:2]
    out = np.empty((h, w), np.float32)
    for r0, r1, a0, a1 in strips(normals.shape, gaussian_reach(max(sigmas))):
        todo = [s for k, s in enumerate(sigmas) if not (k == 0 and finest is not None)]
        stack = weighted_stack(normals[a0:a1], mask[a0:a1], foreshortening=foreshortening, weight=False) \
            if todo else None
        levels = [np.ascontiguousarray(finest[r0:r1])] if finest is not None else []
        for s in todo:
            b = _blur_direct(stack, float(s))[r0 - a0:r1 - a0]
            levels.append(unit_rows(b, out=b))
        del stack
        if partner is not None:   # interpolated, not made unit: the term divides by its length
            levels.append(partner.full((h, w), rows=(r0, r1)))
        ls = l[r0:r1] if l.ndim == 3 else l
        t = out[r0:r1]
        t[...] = 0.0
        lit = [dot_light(n, ls) for n in levels]   # n . l of each level, for both of its pairs
        for k in range(len(levels) - 1):
            term = _exaggerated_term(levels[k], levels[k + 1], ls, a,
                                     unit=partner is None or k + 1 < len(levels) - 1,
                                     fine_l=lit[k], coarse_l=lit[k + 1].copy() if k + 2 < len(levels) else lit[k + 1])
            term *= np.float32(weights[k])
            t += term
        if partner is None and base_weight > 0:
            t += np.float32(base_weight) * np.clip(a * dot_light(levels[-1], ls), -1.0, 1.0)
        del lit, levels
        for term in terms:
            t += term.full((h, w), rows=(r0, r1))
        if scale is not None:
            t *= scale
            t += np.float32(0.5)
    return out


def _exaggerated_term(n_fine: np.ndarray, n_coarse: np.ndarray, l: np.ndarray, a: np.float32, *,
                      unit: bool = True, fine_l: np.ndarray | None = None,
                      coarse_l: np.ndarray | None = None) -> np.ndarray:
    """clamp(a n_i . l_{i+1}, -1, 1) with l_{i+1} = (l - (l.nc) nc) / |...|, |...|^2 = 1 - (l.nc)^2.

    (H, W) float32; computed in place on three (H, W) arrays (the per-pixel n_i . nc as a product
    summed by one matrix-vector product, not einsum's strided loop). ``unit=False``: ``n_coarse``
    is any vector ``v`` along the coarse normal (an interpolated one), ``nc = v / |v|`` taken in
    the products — ``(l.nc)(n_i.nc) = (l.v)(n_i.v) / |v|^2`` — instead of made. ``fine_l``,
    ``coarse_l``: ``n_fine . l`` and ``n_coarse . l`` when the caller has them (a level is the
    fine one of one pair and the coarse one of the next); ``coarse_l`` is overwritten."""
    lc = dot_light(n_coarse, l) if coarse_l is None else coarse_l
    prod = np.multiply(n_fine, n_coarse)
    c = prod @ np.ones(3, np.float32)           # n_i . nc  (n_i . v)
    if not unit:
        np.multiply(n_coarse, n_coarse, out=prod)
        q = prod @ np.ones(3, np.float32)       # |v|^2
        np.maximum(q, np.float32(1e-24), out=q)
        np.reciprocal(q, out=q)
    del prod
    c *= lc
    if not unit:
        c *= q                                  # (l . v)(n_i . v) / |v|^2
    np.subtract(dot_light(n_fine, l) if fine_l is None else fine_l, c, out=c)  # n_i . l - (l . nc)(n_i . nc)
    np.multiply(lc, lc, out=lc)
    if not unit:
        lc *= q                                 # (l . nc)^2
    np.subtract(np.float32(1.0), lc, out=lc)
    np.maximum(lc, np.float32(1e-8), out=lc)
    np.sqrt(lc, out=lc)
    c *= a
    c /= lc
    return np.clip(c, -1.0, 1.0, out=c)


def _chain(first, rest):
    """``first``, then what the generator ``rest`` yields (closing this closes ``rest``)."""
    try:
        yield first
        yield from rest
    finally:
        rest.close()


def _coarse_factor(sigma_px: float, h: int, w: int, enabled: bool = True) -> int:
    """Power-of-two grid step for a level of ``sigma_px``: at most sigma / 2, at least 8 cells a side."""
    f = 1
    while enabled and sigma_px / (2 * f) >= 2.0 and min(h, w) // (2 * f) >= 8:
        f *= 2
    return f


class _WeightedPyramid:
    """The 1/nz-weighted normal stack (w n, w) area-averaged onto grids 2, 4, 8 … times coarser,
    each aligned to the whole image's grid (``origin``: this window's position in it), for
    :func:`exaggerated_shading`'s coarse levels (§7.2.1 smoothing on a coarser grid)."""

    def __init__(self, normals, mask, foreshortening, origin):
        import cv2
        self._cv2 = cv2
        self.origin = (int(origin[0]), int(origin[1]))
        self.shape = normals.shape[:2]
        # grid 2 straight from the normals, strip by strip (2x2 means of the aligned cells, the
        # same as halving a full-resolution stack, which is never made)
        o = self.offset(2)
        hh, ww = self.grid_shape(2)
        small = np.empty((hh, ww, 4), np.float32)
        for i0, i1, _, _ in strips((hh, 2 * ww), 0, pixels=1 << 19):
            rows = slice(o[0] + 2 * i0, o[0] + 2 * i1)
            cols = slice(o[1], o[1] + 2 * ww)
            st = weighted_stack(normals[rows, cols], mask[rows, cols], foreshortening=foreshortening)
            small[i0:i1] = cv2.resize(st, (ww, i1 - i0), interpolation=cv2.INTER_AREA).reshape(i1 - i0, ww, 4)
        self.stacks = {2: small}

    def offset(self, f: int) -> tuple[int, int]:
        return (int(-self.origin[0]) % f, int(-self.origin[1]) % f)

    def stack(self, f: int) -> np.ndarray:
        """The stack on grid ``f``, by halving the finest grid kept so far (2x2 means of the
        aligned cells: the mean over the f x f block, as from full resolution); grids finer than
        the one asked for are released (the levels are asked for from fine to coarse)."""
        while f not in self.stacks:
            g = max(self.stacks)
            if g >= f:
                raise ValueError(f"grid {f} asked for after the coarser grid {g}")
            h, w = self.shape
            o_g, o_2 = self.offset(g), self.offset(2 * g)
            d = ((o_2[0] - o_g[0]) // g, (o_2[1] - o_g[1]) // g)
            hh, ww = (h - o_2[0]) // (2 * g), (w - o_2[1]) // (2 * g)
            cells = self.stacks.pop(g)[d[0]:d[0] + 2 * hh, d[1]:d[1] + 2 * ww]
            self.stacks[2 * g] = self._cv2.resize(np.ascontiguousarray(cells), (ww, hh),
                                                  interpolation=self._cv2.INTER_AREA)
        return self.stacks[f]

    def grid_shape(self, f: int) -> tuple[int, int]:
        h, w = self.shape
        o = self.offset(f)
        return ((h - o[0]) // f, (w - o[1]) // f) if f > 1 else (h, w)

    def resample(self, values: np.ndarray, f_from: int, f_to: int) -> np.ndarray:
        """Unit normals on grid ``f_from`` brought to the finer grid ``f_to`` (bilinear, renormalised)."""
        from common.render.enhance import Coarse
        o_a, o_b = self.offset(f_from), self.offset(f_to)
        off = ((o_a[0] - o_b[0]) // f_to, (o_a[1] - o_b[1]) // f_to)
        return unit_rows(Coarse(values, f_from // f_to, off).full(self.grid_shape(f_to)))

    def level(self, sigma_px: float, f: int) -> np.ndarray:
        """Unit normals smoothed at ``sigma_px`` (full-resolution pixels) on grid ``f``."""
        from common.rgbn._filters import gaussian_blur
        st = self.stack(f)
        # the box average of the grid already holds (f^2 - 1) / 12 of the variance
        s = np.sqrt(max(sigma_px ** 2 - (f * f - 1) / 12.0, 0.25 * f * f)) / f
        b = gaussian_blur(st, float(s))
        out = unit_rows(b)
        empty = b[..., 3] <= 1e-6 * max(float(st[..., 3].max(initial=0.0)), 1e-12)
        if empty.any():
            out[empty] = (0.0, 0.0, 1.0)
        return out


def mean_curvature_shading(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None,
                           sigma_mm: float = 0.0, radius_mm: float | None = 2.0) -> np.ndarray:
    """Mean curvature shading: convex regions light, concave dark, flat mid-grey (§7.3.6).

    ``shade = 0.5 + 0.5 * tanh(H * radius_mm)`` with H the mean curvature in 1/mm (eq. 7.7):
    a plane is uniformly 0.5; a sphere of radius ``radius_mm`` shows at 0.88. With
    ``radius_mm=None`` the contrast adapts to the data (:func:`auto_gain`).

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    dpi : float
        Sampling density (curvature in physical units).
    mask : (H, W) bool, optional
        Pixels carrying normals; 0.5 outside.
    sigma_mm : float
        Foreshortening-corrected pre-smoothing (the curvature scale), mm.
    radius_mm : float or None
        Radius of curvature that maps to tanh(1): the contrast; None = automatic.

    Returns
    -------
    (H, W) float32 in [0, 1]

    References
    ----------
    Toler-Franklin 2011, §7.3.6; Kindlmann et al., "Curvature-based transfer functions for direct
    volume rendering", IEEE Vis 2003.

    Examples
    --------
    >>> n = np.zeros((16, 16, 3), np.float32); n[..., :] = (0.6, 0.0, 0.8)
    >>> float(mean_curvature_shading(n, dpi=300).min()), float(mean_curvature_shading(n, dpi=300).max())
    (0.5, 0.5)
    """
    normals = check_normals(normals)
    dpi = check_dpi(dpi)
    mask = check_mask(mask, normals.shape[:2])
    if sigma_mm < 0:
        raise ValueError(f"sigma_mm must be >= 0, got {sigma_mm}")
    if radius_mm is not None and not radius_mm > 0:
        raise ValueError(f"radius_mm must be > 0 or None, got {radius_mm}")
    H = mean_curvature(normals, dpi, mask=mask, sigma_px=sigma_mm * dpi / 25.4)
    gain = auto_gain(H, mask) if radius_mm is None else np.float32(radius_mm)
    return (0.5 + 0.5 * np.tanh(H * gain)).astype(np.float32)


def auto_gain(values: np.ndarray, mask: np.ndarray, *, percentile: float = 95.0, target: float = 1.5) -> np.float32:
    """Gain that maps the ``percentile`` of ``|values|`` on the mask to ``target`` (1 if all zero)."""
    v = np.abs(values[mask]) if mask.any() else np.abs(values).ravel()
    ref = float(np.percentile(v, percentile)) if v.size else 0.0
    return np.float32(target / ref) if ref > 1e-12 else np.float32(1.0)


def multiscale_mean_curvature_shading(normals: np.ndarray, dpi: float, *, mask: np.ndarray | None = None,
                                      scales: int = 5, sigma0_mm: float = 0.1, sigma_ratio: float = 2.0,
                                      gain: float | None = None, detail: float = 0.0,
                                      raw: bool = False, origin=(0, 0), coarse: bool = True) -> np.ndarray:
    """Multiscale mean curvature shading (eq. 7.8): curvature at all scales in one picture.

    ``shade = 0.5 + 0.5 * tanh(gain * sum_i w_i * sigma_i * H_i)`` where ``H_i`` is the mean
    curvature (1/mm) of the normals smoothed at ``sigma_i = sigma0_mm * ratio^i`` and the weights
    ``w_i ∝ sigma_i^-detail`` sum to 1. Multiplying by ``sigma_i`` makes each term dimensionless
    (a bump of width sigma_i contributes about equally at its own scale), so coarse shape and fine
    tool marks appear together. ``gain=None`` adapts the contrast to the data (:func:`auto_gain`).
    ``raw=True`` returns the weighted sum itself (before gain and tanh); 0 outside the mask.

    Parameters
    ----------
    origin : (int, int)
        Row and column of this window in the whole image (tiles): the coarse grids are aligned to
        the whole image's, so overlapping tiles draw the same values.
    coarse : bool
        Compute a level whose sigma is >= 8 px on a grid 2, 4, … times coarser (sigma >= 4 grid
        steps there, where central differences are within ~1 % of the derivative), and bring its
        curvature back by bilinear interpolation (default; test: within 1/255 of the full-resolution
        picture). False computes every level at full resolution (the reference).

    Returns
    -------
    (H, W) float32 in [0, 1]; a plane is uniformly 0.5.

    References
    ----------
    Toler-Franklin 2011, §7.3.6, eq. 7.8; Toler-Franklin et al., NPAR 2007, §4.3.

    Notes
    -----
    The per-scale normalization by ``sigma_i`` and the ``tanh`` soft clamp are this
    implementation's choices for the weights of eq. 7.8. All levels come from one weighted normal
    stack (the 1/nz-weighted smoothing of §7.2.1), smoothed once per level.
    """
    normals = check_normals(normals)
    dpi = check_dpi(dpi)
    mask = check_mask(mask, normals.shape[:2])
    if int(scales) != scales or scales < 1:
        raise ValueError(f"scales must be an integer >= 1, got {scales}")
    if not sigma0_mm > 0:
        raise ValueError(f"sigma0_mm must be > 0, got {sigma0_mm}")
    if not sigma_ratio > 1:
        raise ValueError(f"sigma_ratio must be > 1, got {sigma_ratio}")
    sigmas = [sigma0_mm * sigma_ratio ** i for i in range(int(scales))]
    w = np.array([s ** -detail for s in sigmas])
    w /= w.sum()
    h, wd = normals.shape[:2]
    px = [s * dpi / 25.4 for s in sigmas]
    grids = [_curvature_grid(p, h, wd, coarse) for p in px]
    full = [(wi * s, p) for wi, s, p, f in zip(w, sigmas, px, grids) if f == 1]
    total = _curvature_full(normals, mask, dpi, full) if full else np.zeros((h, wd), np.float32)
    if len(full) < len(sigmas):
        pyramid = _WeightedPyramid(normals, mask, True, origin)
        acc: dict = {}
        for wi, s, p, f in zip(w, sigmas, px, grids):
            if f == 1:
                continue
            H = mean_curvature(pyramid.level(p, f), dpi / f)
            H *= np.float32(wi * s)
            if f in acc:
                acc[f] += H
            else:
                acc[f] = H
            del H
        for f, term in acc.items():
            total += Coarse(term, f, pyramid.offset(f)).full((h, wd))
    total[~mask] = 0.0
    if raw:
        return total
    g = auto_gain(total, mask) if gain is None else np.float32(gain)
    return (0.5 + 0.5 * np.tanh(g * total)).astype(np.float32)


def _curvature_full(normals, mask, dpi, levels):
    """Sum of ``k * H(sigma)`` over ``levels`` = [(k, sigma_px), ...] at full resolution, row
    strip by row strip (each strip smoothed from its rows and a halo of the widest kernel's reach
    plus the derivative's two rows, so no temporary is of the image's size). (H, W) float32.

    Only ``w n`` is blurred (:func:`common.rgbn.smoothing.weighted_stack` without its weight): a
    mask pixel's curvature reads its neighbours one pixel away, always within reach of the mask,
    so where no mask pixel is in reach (what the blurred weight would tell) is never read, and
    the sum is 0 off the mask."""
    h, w = normals.shape[:2]
    out = np.empty((h, w), np.float32)
    for r0, r1, a0, a1 in strips(normals.shape, gaussian_reach(max(p for _, p in levels)) + 2):
        e0, e1 = max(0, r0 - 2), min(h, r1 + 2)   # the rows the derivatives of r0:r1 read
        stack = weighted_stack(normals[a0:a1], mask[a0:a1], weight=False)
        t = out[r0:r1]
        t[...] = 0.0
        for k, p in levels:
            b = _blur_direct(stack, float(p))[e0 - a0:e1 - a0]
            H = mean_curvature(unit_rows(b, out=b), dpi)
            t += np.float32(k) * H[r0 - e0:r1 - e0]
    return out


def _curvature_grid(sigma_px: float, h: int, w: int, enabled: bool = True) -> int:
    """Power-of-two grid step for a curvature level of ``sigma_px``: sigma stays >= 4 grid steps
    (central differences there are within ~1 % of the derivative), at least 8 cells a side."""
    f = 1
    while enabled and sigma_px / (2 * f) >= 4.0 and min(h, w) // (2 * f) >= 8:
        f *= 2
    return f


def _check_colour(colour, shape) -> np.ndarray:
    c = np.asarray(colour, dtype=np.float32)
    if c.shape != tuple(shape) + (3,):
        raise ValueError(f"colour image must be {tuple(shape) + (3,)}, got {c.shape}")
    return c
