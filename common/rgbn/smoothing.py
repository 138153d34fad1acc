"""Gaussian smoothing and scale space of RGBN images with the foreshortening correction (§7.2).

A pixel of a normal map covers a surface area proportional to ``1 / nz``: a patch tilted away
from the viewer is foreshortened into fewer pixels. Averaging normals with plain image-space
weights therefore under-represents steep surface; the thesis (§7.2.1) weights every sample by
``1 / nz`` so that the filter averages over surface area rather than over pixels.
"""

from __future__ import annotations

import numpy as np

from common.rgbn._filters import (_blur_direct, blurs_directly, check_mask, check_normals, decimated_sigma,
                                  decimation_factor, gaussian_blur, gaussian_reach, upsampled_rows)

#: Smallest nz used in the 1/nz weight: silhouette pixels (nz -> 0) would otherwise dominate.
NZ_MIN = 0.05
#: Pixels of one strip when a full-resolution smoothing is computed strip by strip (rows with a
#: halo of the kernel's reach): its temporaries (~60 bytes a pixel) then stay in the processor's
#: cache and in memory already mapped, instead of being page-faulted in at the size of the image
#: (at 12 Mpx a fresh 144 MB array costs ~35,000 faults).
STRIP_PIXELS = 1 << 20


def foreshortening_weights(normals: np.ndarray, mask: np.ndarray | None = None, *,
                           nz_min: float = NZ_MIN) -> np.ndarray:
    """Per-pixel surface-area weight ``1 / max(nz, nz_min)`` (0 outside ``mask``), §7.2.1."""
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    if not 0 < nz_min <= 1:
        raise ValueError(f"nz_min must be in (0, 1], got {nz_min}")
    # in place on one contiguous plane: the same values as 1 / max(nz, nz_min), 0 off the mask
    w = np.maximum(normals[..., 2], np.float32(nz_min))
    np.reciprocal(w, out=w)
    np.multiply(w, mask, out=w)
    return w


def smooth_normals(normals: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None,
                   foreshortening: bool = True, nz_min: float = NZ_MIN) -> np.ndarray:
    """Gaussian smoothing of a normal map with the 1/nz foreshortening correction.

    Computes ``n'(p) = normalize( sum_q G_sigma(p - q) w(q) n(q) )`` with
    ``w(q) = mask(q) / nz(q)`` (thesis §7.2.1): a normalized convolution, so pixels outside the
    mask neither contribute nor darken the border.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals, x right, y up, z towards the viewer.
    sigma_px : float
        Standard deviation of the Gaussian in pixels (``sigma_mm * dpi / 25.4``). 0 returns a copy.
    mask : (H, W) bool, optional
        Pixels that carry a normal; others are ignored and filled from their neighbours.
    foreshortening : bool
        Weight samples by ``1 / nz`` (True, the thesis' choice) or uniformly.
    nz_min : float
        Lower bound of nz in the weight.

    Returns
    -------
    (H, W, 3) float32
        Unit normals. Inside the mask the smoothed normal; outside it the smoothed extrapolation
        where any mask pixel is within reach, else the input.

    References
    ----------
    Toler-Franklin 2011, §7.2.1 (RGBN smoothing, eq. 7.1); Toler-Franklin et al., "Illustration of
    complex real-world objects using images with normals", NPAR 2007, §3.1.

    Examples
    --------
    >>> n = np.zeros((32, 32, 3), np.float32); n[..., 2] = 1
    >>> bool(np.allclose(smooth_normals(n, 2.0), n))
    True
    """
    normals = check_normals(normals)
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px}")
    mask = check_mask(mask, normals.shape[:2])
    if sigma_px == 0:
        return normals.copy()
    return next(iter_scale_space(normals, [sigma_px], mask=mask, foreshortening=foreshortening, nz_min=nz_min))


def weighted_stack(normals: np.ndarray, mask: np.ndarray | None = None, *, foreshortening: bool = True,
                   nz_min: float = NZ_MIN, weight: bool = True) -> np.ndarray:
    """The (H, W, 4) float32 stack ``(w n, w)`` whose Gaussian blur, normalised, is the smoothed
    normal field (§7.2.1): ``w = mask / max(nz, nz_min)`` (``mask`` alone without foreshortening).
    One stack serves every scale of a scale space, and coarser grids of it
    (:class:`common.render.shading._WeightedPyramid`). ``weight=False``: only ``w n``, (H, W, 3),
    for a caller that needs the smoothed directions but not where no mask pixel is in reach (the
    blurred weight tells that; OpenCV blurs three channels a quarter faster than four, to the
    same values)."""
    import cv2

    normals = np.ascontiguousarray(check_normals(normals))
    mask = check_mask(mask, normals.shape[:2])
    w = foreshortening_weights(normals, mask, nz_min=nz_min) if foreshortening else mask.astype(np.float32)
    h, wd = normals.shape[:2]
    if not weight:
        return cv2.multiply(normals, cv2.merge([w, w, w])).reshape(h, wd, 3)
    # (n, 1) by OpenCV's alpha channel, then times (w, w, w, w): one interleaved pass each
    stack = cv2.cvtColor(normals, cv2.COLOR_BGR2BGRA).reshape(h, wd, 4)
    cv2.multiply(stack, cv2.merge([w, w, w, w]).reshape(h, wd, 4), dst=stack)
    return stack


def iter_scale_space(normals: np.ndarray, sigmas_px, *, mask: np.ndarray | None = None,
                     foreshortening: bool = True, nz_min: float = NZ_MIN):
    """Yield :func:`smooth_normals` at each sigma in turn (§7.2.1).

    Only one level is alive at a time unless the caller keeps it, which bounds the memory of
    many-scale styles on 16-Mpx images. A sigma that :func:`common.rgbn._filters.gaussian_blur`
    applies at full resolution is computed in row strips (:func:`smoothed_rows`), so the
    weighted stack and its blur never exist at the image's size; larger sigmas share one
    full-size weighted stack (made when the first of them comes).
    """
    normals = check_normals(normals)
    mask = check_mask(mask, normals.shape[:2])
    floor = weight_floor(normals, mask, foreshortening=foreshortening, nz_min=nz_min)
    stack = None
    for sigma in sigmas_px:
        if not np.isfinite(sigma) or sigma < 0:
            raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma}")
        if sigma == 0:
            yield normals.copy()
            continue
        if blurs_directly(sigma, normals.shape):
            out = np.empty(normals.shape, np.float32)
            for r0, r1, a0, a1 in strips(normals.shape, gaussian_reach(sigma)):
                smoothed_rows(normals, mask, float(sigma), (r0, r1), (a0, a1), floor,
                              foreshortening=foreshortening, nz_min=nz_min, out=out[r0:r1])
            yield out
            continue
        if stack is None:
            stack = weighted_stack(normals, mask, foreshortening=foreshortening, nz_min=nz_min)
        blurred = gaussian_blur(stack, float(sigma))
        # where no mask pixel is in reach the weight sum vanishes: keep the input there
        empty = blurred[..., 3] <= floor
        out = unit_rows(blurred)
        del blurred
        if empty.any():
            copy_where(out, normals, empty)
        yield out


def smoothed_cosines(normals: np.ndarray, sigma_px: float, directions, *, mask: np.ndarray | None = None,
                     foreshortening: bool = True, nz_min: float = NZ_MIN) -> list[np.ndarray]:
    """``n_s . d`` per pixel for each direction ``d``, with ``n_s`` the normals smoothed at
    ``sigma_px`` (:func:`smooth_normals`, §7.2.1): the Lambertian cosine of the smoothed surface
    under a light, without making the smoothed normals.

    The smoothed normal is the direction of the blurred weighted stack ``b = G * (w n)``, so
    ``n_s . d = (b . d) / |b|``. A sigma blurred at full resolution is computed in row strips
    (:func:`strips`), so neither the stack nor its blur exists at the image's size; a larger one
    blurs the whole stack (:func:`common.rgbn._filters.gaussian_blur`) and divides it strip by strip.

    Parameters
    ----------
    normals : (H, W, 3) float
        Unit normals.
    sigma_px : float
        Gaussian sigma in pixels, >= 0 (0: the normals as they are).
    directions : list
        Each a unit 3-vector, or a callable ``(r0, r1) -> (r1 - r0, W, 3)`` giving unit vectors for
        those rows (a per-pixel light, such as a levelled one).
    mask : (H, W) bool, optional

    Returns
    -------
    list of (H, W) float32
        One cosine per direction (the input normal's where no mask pixel is within reach, as
        :func:`smooth_normals` keeps the input there).
    """
    import cv2

    normals = check_normals(normals)
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px}")
    mask = check_mask(mask, normals.shape[:2])
    h, w = normals.shape[:2]
    out = [np.empty((h, w), np.float32) for _ in directions]
    direct = sigma_px > 0 and blurs_directly(sigma_px, normals.shape)
    floor = weight_floor(normals, mask, foreshortening=foreshortening, nz_min=nz_min)
    blurred_of = None   # rows r0:r1 of the blurred stack, for a sigma blurred on a coarser grid
    if sigma_px > 0 and not direct:
        f = decimation_factor(sigma_px, normals.shape)
        if h % f == 0 and w % f == 0:
            # gaussian_blur's own steps, with neither the stack nor its blur at the image's size:
            # the f x f area means (INTER_AREA at a whole factor) strip by strip, the blur on that
            # grid, and each strip's rows of the bilinear upsampling; the same values
            small = np.empty((h // f, w // f, 4), np.float32)
            for i0, i1, _, _ in strips((h // f, w * f), 0):   # ~1 Mpx of the image at a time
                st = weighted_stack(normals[i0 * f:i1 * f], mask[i0 * f:i1 * f], foreshortening=foreshortening,
                                    nz_min=nz_min)
                small[i0:i1] = cv2.resize(st, (w // f, i1 - i0), interpolation=cv2.INTER_AREA).reshape(i1 - i0, -1, 4)
            small = _blur_direct(small, decimated_sigma(sigma_px, f))

            def blurred_of(r0, r1):
                return upsampled_rows(small, (h, w), (r0, r1))
        else:
            whole = gaussian_blur(weighted_stack(normals, mask, foreshortening=foreshortening, nz_min=nz_min),
                                  float(sigma_px))

            def blurred_of(r0, r1):
                return whole[r0:r1]
    ones = np.ones(3, np.float32)

    def dot(x, v):   # x . v per pixel, v a vector or a field of the rows' vectors
        return x @ v if v.ndim == 1 else np.multiply(x, v) @ ones

    for r0, r1, a0, a1 in strips(normals.shape, gaussian_reach(sigma_px) if direct else 0):
        if sigma_px == 0:
            b, empty, inv = np.ascontiguousarray(normals[r0:r1]), None, None
        else:
            if direct:
                b, empty = blurred_rows(normals, mask, float(sigma_px), (r0, r1), (a0, a1), floor,
                                        foreshortening=foreshortening, nz_min=nz_min)
            else:
                b = blurred_of(r0, r1)
                empty = b[..., 3] <= floor
            b = cv2.cvtColor(b, cv2.COLOR_BGRA2BGR)   # (w n): contiguous, the weight dropped
            inv = np.multiply(b, b) @ ones
            np.sqrt(inv, out=inv)
            np.maximum(inv, np.float32(1e-12), out=inv)
            np.reciprocal(inv, out=inv)
        for d, cos in zip(directions, out):
            v = d(r0, r1) if callable(d) else np.asarray(d, np.float32)
            c = cos[r0:r1]
            c[...] = dot(b, v)
            if inv is not None:
                c *= inv
                if empty.any():   # as smooth_normals, the input normal where no mask pixel is in reach
                    np.copyto(c, dot(np.ascontiguousarray(normals[r0:r1]), v), where=empty)
    return out


def weight_floor(normals: np.ndarray, mask: np.ndarray, *, foreshortening: bool = True,
                 nz_min: float = NZ_MIN) -> np.float32:
    """A millionth of the largest smoothing weight of the image (1 / the smallest nz on the mask):
    a blurred weight sum at or below it means no mask pixel within reach."""
    if not mask.any():
        wmax = 0.0
    elif foreshortening:
        nz = np.min(normals[..., 2], where=mask, initial=np.float32(np.inf))
        wmax = float(np.float32(1.0) / np.maximum(np.float32(nz), np.float32(nz_min)))
    else:
        wmax = 1.0
    return np.float32(1e-6 * max(wmax, 1e-12))


def strips(shape, halo: int, pixels: int | None = None):
    """Row strips of an image of ``shape`` for a filter that reads ``halo`` rows on each side:
    yields ``(r0, r1, a0, a1)``, the strip's rows and the rows to read (clipped to the image).
    A strip holds about ``pixels`` pixels (None: :data:`STRIP_PIXELS`) and at least 4 halos of rows."""
    h, w = shape[:2]
    pixels = STRIP_PIXELS if pixels is None else pixels
    rows = max(4 * int(halo), pixels // max(int(w), 1), 16)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        yield r0, r1, max(0, r0 - halo), min(h, r1 + halo)


def smoothed_rows(normals: np.ndarray, mask: np.ndarray, sigma_px: float, rows, window, floor, *,
                  stack: np.ndarray | None = None, foreshortening: bool = True, nz_min: float = NZ_MIN,
                  out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``r0:r1`` (``rows``) of :func:`smooth_normals`, computed from rows ``a0:a1``
    (``window``) only: exact for a sigma blurred at full resolution when the window reaches
    :func:`common.rgbn._filters.gaussian_reach` of it beyond the rows (the kernel never reads
    past it; :func:`strips` gives such windows). ``floor``: :func:`weight_floor` of the whole
    image; ``stack``: :func:`weighted_stack` of the window's rows, when the caller smooths them at
    several sigmas; ``out``: a contiguous (r1 - r0, W, 3) float32 array to write to.
    Returns the (r1 - r0, W, 3) float32 unit normals."""
    b, empty = blurred_rows(normals, mask, sigma_px, rows, window, floor, stack=stack,
                            foreshortening=foreshortening, nz_min=nz_min)
    res = unit_rows(b, out=out)
    if empty.any():
        copy_where(res, np.ascontiguousarray(normals[rows[0]:rows[1]]), empty)
    return res


def blurred_rows(normals: np.ndarray, mask: np.ndarray, sigma_px: float, rows, window, floor, *,
                 stack: np.ndarray | None = None, foreshortening: bool = True, nz_min: float = NZ_MIN):
    """The blurred weighted stack ``G * (w n, w)`` of rows ``r0:r1`` before normalisation, (r1 - r0,
    W, 4) float32, and where no mask pixel is within reach ((r1 - r0, W) bool: there
    :func:`smoothed_rows` keeps the input): for a caller that needs only a function of the
    smoothed normal's direction, such as its cosine with a light (the arguments as
    :func:`smoothed_rows`)."""
    (r0, r1), (a0, a1) = rows, window
    if stack is None:
        stack = weighted_stack(normals[a0:a1], mask[a0:a1], foreshortening=foreshortening, nz_min=nz_min)
    b = _blur_direct(stack, float(sigma_px))[r0 - a0:r1 - a0]
    return b, b[..., 3] <= floor


def unit_rows(blurred: np.ndarray, *, out: np.ndarray | None = None) -> np.ndarray:
    """The first three channels of an (H, W, 4) or (H, W, 3) float32 array as unit vectors,
    (H, W, 3) float32 (zero vectors -> 0): ``v / max(|v|, 1e-12)``, as a product with the
    reciprocal length. The squared lengths are one matrix-vector product; the channels are
    taken out and scaled by OpenCV, which, unlike numpy, does not slow down on an interleaved
    last axis. ``out``: a contiguous (H, W, 3) float32 array to write to."""
    import cv2

    if blurred.ndim != 3 or blurred.shape[2] not in (3, 4):
        raise ValueError(f"expected an (H, W, 3) or (H, W, 4) array, got shape {blurred.shape}")
    b = np.ascontiguousarray(blurred, np.float32)
    c = b.shape[2]
    inv = np.multiply(b, b) @ np.array([1.0, 1.0, 1.0, 0.0][:c], np.float32)   # |v|^2
    np.sqrt(inv, out=inv)
    np.maximum(inv, 1e-12, out=inv)
    np.reciprocal(inv, out=inv)
    shape = b.shape[:2] + (3,)
    if out is None:
        out = np.empty(shape, np.float32)
    if c == 4:
        cv2.cvtColor(b, cv2.COLOR_BGRA2BGR, dst=out)   # drops the fourth channel, order kept
    else:
        np.copyto(out, b)
    cv2.multiply(out, cv2.merge([inv, inv, inv]), dst=out)
    return out


def copy_where(dst: np.ndarray, src: np.ndarray, where: np.ndarray) -> np.ndarray:
    """``dst[where] = src[where]`` in place, ``where`` an (H, W) bool mask and ``dst``, ``src``
    (H, W) or (H, W, C) arrays of one dtype: OpenCV's masked copy (one pass, no gather of the
    selected pixels) when ``dst`` is contiguous, else numpy's. Returns ``dst``."""
    import cv2

    where = np.asarray(where, bool)
    if (dst.flags.c_contiguous and src.shape == dst.shape and src.dtype == dst.dtype
            and where.shape == dst.shape[:2] and dst.ndim in (2, 3) and (dst.ndim == 2 or dst.shape[2] <= 4)):
        cv2.copyTo(np.ascontiguousarray(src), np.ascontiguousarray(where).view(np.uint8), dst)
    else:
        np.copyto(dst, src, where=where[..., None] if dst.ndim == 3 and where.ndim == 2 else where)
    return dst


def smooth_albedo(albedo: np.ndarray, sigma_px: float, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Masked (normalized-convolution) Gaussian smoothing of an (H, W, C) colour image."""
    albedo = np.asarray(albedo, dtype=np.float32)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    if albedo.ndim != 3:
        raise ValueError(f"albedo must be (H, W) or (H, W, C), got shape {albedo.shape}")
    if not np.isfinite(sigma_px) or sigma_px < 0:
        raise ValueError(f"sigma_px must be a finite number >= 0, got {sigma_px}")
    mask = check_mask(mask, albedo.shape[:2])
    if sigma_px == 0:
        return albedo.copy()
    w = mask.astype(np.float32)
    blurred = gaussian_blur(np.concatenate([albedo * w[..., None], w[..., None]], axis=2), sigma_px)
    den = blurred[..., -1:]
    out = np.where(den > 1e-6, blurred[..., :-1] / np.maximum(den, 1e-6), albedo)
    return out.astype(np.float32, copy=False)


def scale_space(normals: np.ndarray, sigmas_px, *, mask: np.ndarray | None = None,
                foreshortening: bool = True) -> list[np.ndarray]:
    """Normals smoothed at each of ``sigmas_px`` (a Gaussian scale space, §7.2.1).

    Each level is computed from the input (not cascaded), so level ``i`` is exactly
    :func:`smooth_normals` at ``sigmas_px[i]``; large sigmas run on a downsampled grid, so the
    cost per level is roughly constant.

    Returns
    -------
    list of (H, W, 3) float32
        One unit-normal map per sigma, in the given order.
    """
    sigmas = [float(s) for s in np.atleast_1d(sigmas_px)]
    if not sigmas:
        raise ValueError("sigmas_px must hold at least one sigma")
    return list(iter_scale_space(normals, sigmas, mask=mask, foreshortening=foreshortening))


def smooth_rgbn(image, sigma_mm: float, *, foreshortening: bool = True):
    """Smooth an :class:`~common.rgbn.image.RGBNImage`: albedo and normals at ``sigma_mm``.

    The pixel sigma is ``sigma_mm * dpi / 25.4``. Returns a new RGBNImage (other channels kept).
    """
    from dataclasses import replace

    if not np.isfinite(sigma_mm) or sigma_mm < 0:
        raise ValueError(f"sigma_mm must be a finite number >= 0, got {sigma_mm}")
    sigma_px = sigma_mm / image.pixel_mm
    albedo = smooth_albedo(image.albedo, sigma_px, mask=image.mask)
    normals = None
    if image.normals is not None:
        normals = smooth_normals(image.normals, sigma_px, mask=image.mask, foreshortening=foreshortening)
    return replace(image, albedo=albedo, normals=normals)
