"""Photometric stereo from images under known distant lights (thesis §3.2, eq. 3.2).

A Lambertian pixel lit from unit direction :math:`l_i` has intensity

.. math:: I_i = \\rho \\, \\max(0, l_i \\cdot n) = l_i \\cdot g, \\qquad g = \\rho n   \\qquad \\text{(eq. 3.2)}

With N ≥ 3 lights the scaled normal :math:`g` follows by least squares; :math:`\\rho = |g|`,
:math:`n = g / |g|` (Woodham 1980). Real captures break the model where a pixel is in shadow
(attached or cast: the max(0, ·) clips) or shows a specular highlight; with the 30–100 lights of
a hand-held or RTI capture there is enough redundancy to drop those measurements per pixel
(:func:`robust_normals`).

Two public solvers, both vectorised over pixels (no Python loop per pixel):

* :func:`least_squares_normals` — one pseudo-inverse of the light matrix for all pixels;
* :func:`robust_normals` — per-pixel intensity-rank trimming, then iteratively re-weighted
  least squares that drops lights below the pixel's shadow terminator and residual outliers
  (highlights), each iteration one batched 3×3 solve.

Both return an :class:`~common.rgbn.image.RGBNImage` in the project convention (normals x right,
y up, z towards the viewer; row 0 at the top), with RGB albedo and a confidence map.
"""

from __future__ import annotations

import functools
from typing import Callable

import numpy as np

from common.rgbn.image import RGBNImage
from common.threads import one_blas_thread

#: Luminance weights (ITU-R BT.601, as MATLAB's rgb2gray) used to solve normals from colour
#: images; with them the DiLiGenT least-squares baseline is reproduced.
LUMA = np.array([0.2989, 0.5870, 0.1140], dtype=np.float32)

_CHUNK = 1 << 14  # pixels per block: temporaries of N × 16 Ki floats stay in cache


def _one_blas_thread(func):
    """Run ``func`` with BLAS limited to one thread (:mod:`common.threads`): the solvers' products
    are tall and skinny ((P, N) × (N, 6)), memory-bound."""
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        with one_blas_thread():
            return func(*args, **kwargs)
    return wrapper


def _check_inputs(images, directions, mask, valid, positions=None):
    if (directions is None) == (positions is None):
        raise ValueError("give exactly one of directions (distant lights) or positions (near lights)")
    if positions is not None:
        positions = np.asarray(positions, np.float64)
        if positions.ndim != 2 or positions.shape[1] != 3 or np.any(positions[:, 2] <= 0):
            raise ValueError(f"positions must be (N, 3) with z > 0 (in front of the object), got {positions.shape}")
        directions = positions
    images = np.asarray(images)
    if images.ndim not in (3, 4) or (images.ndim == 4 and images.shape[3] != 3):
        raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got shape {images.shape}")
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"images must be floating point (linear intensities), got {images.dtype}")
    n, h, w = images.shape[:3]
    d = np.asarray(directions, dtype=np.float64)
    if d.shape != (n, 3):
        raise ValueError(f"directions must be ({n}, 3) for {n} images, got {d.shape}")
    norm = np.linalg.norm(d, axis=1)
    if not np.all(np.isfinite(d)) or np.any(norm < 1e-6):
        raise ValueError("directions must be finite and non-zero")
    d = d / norm[:, None]
    if n < 3 or np.linalg.matrix_rank(d, tol=1e-3) < 3:
        raise ValueError(f"directions must span 3-D (at least 3 non-coplanar lights), got {n} of rank "
                         f"{np.linalg.matrix_rank(d, tol=1e-3)}")
    if mask is None:
        mask = np.ones((h, w), bool)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask must be {(h, w)}, got {mask.shape}")
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        if valid.shape != (n, h, w):
            raise ValueError(f"valid must be {(n, h, w)}, got {valid.shape}")
    return images, d.astype(np.float32), mask, valid


def _pixels(images, idx):
    """Grey (P, N) pixel-major intensities and colour (N, P, C) of the pixels ``idx`` (flat)."""
    n = images.shape[0]
    flat = images.reshape(n, -1, *images.shape[3:])
    if len(idx) and idx[-1] - idx[0] + 1 == len(idx):
        colour = flat[:, idx[0]:idx[-1] + 1]  # a run of pixels: a view, no gather
    else:
        colour = flat[:, idx]
    colour = colour.astype(np.float32, copy=False)
    if colour.ndim == 2:
        colour = colour[..., None]
        grey = colour[..., 0]
    else:
        grey = colour[..., 0] * LUMA[0] + colour[..., 1] * LUMA[1] + colour[..., 2] * LUMA[2]
    # pixel-major: per-pixel reductions and sorts over the lights run on contiguous memory
    return np.ascontiguousarray(grey.T), colour


def _unit(g):
    rho = np.linalg.norm(g, axis=-1)
    n = g / np.maximum(rho, 1e-12)[..., None]
    return n, rho


def _solve_sym3(a, b):
    """Solve P symmetric 3×3 systems ``a (P, 6: xx xy xz yy yz zz) · g = b (P, 3)`` by cofactors.

    Closed form in float64: much faster than a batched LAPACK call for 3×3 matrices.
    """
    a = a.astype(np.float64)
    b = b.astype(np.float64)
    a00, a01, a02, a11, a12, a22 = (a[:, k] for k in range(6))
    c00 = a11 * a22 - a12 * a12
    c01 = a02 * a12 - a01 * a22
    c02 = a01 * a12 - a02 * a11
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    # pixels with < 3 usable lights have det ≈ 0: they come out as 0 and get confidence 0
    inv = np.where(np.abs(det) > 1e-12, 1.0 / np.where(det == 0, 1.0, det), 0.0)
    g = np.empty_like(b)
    g[:, 0] = (c00 * b[:, 0] + c01 * b[:, 1] + c02 * b[:, 2]) * inv
    g[:, 1] = (c01 * b[:, 0] + c11 * b[:, 1] + c12 * b[:, 2]) * inv
    g[:, 2] = (c02 * b[:, 0] + c12 * b[:, 1] + c22 * b[:, 2]) * inv
    return g.astype(np.float32)


_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _weighted_solve(grey, lights, weights):
    """Per-pixel weighted least squares: g_p = (Σ w l lᵀ)⁻¹ Σ w I l, batched (eq. 3.2).

    ``grey`` and ``weights`` are pixel-major (P, N); ``lights`` is (N, 3) shared by every pixel,
    or (P, N, 3) per pixel (near lights).
    """
    if lights.ndim == 3:
        outer = np.stack([lights[..., i] * lights[..., j] for i, j in _SYM], axis=2)  # (P, N, 6)
        return _solve_sym3(np.einsum("pn,pnk->pk", weights, outer), np.einsum("pn,pnk->pk", weights * grey, lights))
    outer = np.stack([lights[:, i] * lights[:, j] for i, j in _SYM], axis=1)  # (N, 6)
    return _solve_sym3(weights @ outer, (weights * grey) @ lights)


def _predict(g, lights):
    """l·g per pixel and light, (P, N), for shared (N, 3) or per-pixel (P, N, 3) lights."""
    return np.einsum("pk,pnk->pn", g, lights) if lights.ndim == 3 else g @ lights.T


def point_light_field(positions, shape, idx=None):
    """Per-pixel direction and 1/r² fall-off of near point lights over the image plane z = 0.

    Parameters
    ----------
    positions : (N, 3) array
        Light positions in pixels: x right and y up from the image centre, z towards the camera.
    shape : (H, W)
        Image size.
    idx : (P,) int array, optional
        Flat pixel indices (default all).

    Returns
    -------
    directions : (P, N, 3) float32
        Unit vectors from each pixel to each light.
    falloff : (P, N) float32
        ``(|p_i| / |p_i − x|)²``: the irradiance relative to the image centre's.

    Examples
    --------
    >>> d, f = point_light_field([[0.0, 0.0, 10.0]], (3, 3))   # a lamp 10 px above the centre
    >>> [round(float(v), 3) for v in d[0, 0]], round(float(f[0, 0]), 3)   # seen from the top-left pixel
    ([0.099, -0.099, 0.99], 0.98)
    """
    pos = np.asarray(positions, np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or not np.all(np.isfinite(pos)) or np.any(pos[:, 2] <= 0):
        raise ValueError(f"positions must be (N, 3), finite, in front of the plane (z > 0), got {pos.shape}")
    h, w = shape
    idx = np.arange(h * w) if idx is None else np.asarray(idx)
    rows, cols = np.divmod(idx, w)
    x = np.stack([cols - (w - 1) / 2.0, (h - 1) / 2.0 - rows, np.zeros(len(idx))], axis=1)  # (P, 3)
    v = pos[None, :, :] - x[:, None, :]
    r2 = np.einsum("pnk,pnk->pn", v, v)
    d = (v / np.sqrt(r2)[..., None]).astype(np.float32)
    return d, ((pos ** 2).sum(1)[None, :] / r2).astype(np.float32)


def _albedo_rgb(colour, lights, normals, weights):
    """Per-channel albedo with the normal fixed: ρ_c = Σ w I_c s / Σ w s², s = max(0, l·n)."""
    shade = np.clip(_predict(normals, lights), 0.0, None)  # (P, N)
    ws = weights * shade
    den = np.maximum(np.einsum("pn,pn->p", ws, shade), 1e-12)
    return np.einsum("pn,npc->pc", ws, colour) / den[:, None]


def _confidence(grey, pred, weights, n_lights, robust):
    """Confidence in [0, 1]: enough (inlier) lights, and a small residual relative to intensity."""
    used = weights.sum(1)
    r = grey - pred
    rss = np.einsum("pn,pn->p", weights * r, r)
    power = np.einsum("pn,pn->p", weights * grey, grey)
    return _confidence_from(used, rss, power, n_lights, robust)


def _confidence_from(used, rss, power, n_lights, robust):
    """``(1 − relative residual)`` × a support factor.

    Least squares: the factor is ``used ≥ 3`` (3 lights determine a normal; docs/handheld.md).
    Robust: ``clip((used − 3) / max(3, N/4), 0, 1)`` — 3 or fewer kept lights give 0, full at
    ``3 + max(3, N/4)`` kept lights (the lights a pixel keeps are evidence it fits the model).
    """
    rel = np.sqrt(np.clip(rss, 0.0, None) / np.maximum(power, 1e-12))
    if robust:
        support = np.clip((used - 3.0) / max(3.0, 0.25 * n_lights), 0.0, 1.0)
    else:
        support = (used >= 3.0 - 1e-3).astype(np.float64)
    return (support * np.clip(1.0 - rel, 0.0, 1.0)).astype(np.float32)


#: fewest images for which :func:`robust_normals` can give any pixel a confidence above 0 (it needs
#: more than 3 kept lights)
ROBUST_MIN_IMAGES = 4


def _least_squares_linear(images, lights, idx_all):
    """Unweighted least squares for the pixels ``idx_all``: one pseudo-inverse for every pixel.

    Everything is linear in the images, so each channel is solved at once (one matrix product
    over the contiguous (N, P·C) data) and the luminance solution is the weighted sum of the
    channel solutions; albedo and residual follow from the 3×3 normal matrix without forming
    predicted images.
    """
    n_img = images.shape[0]
    chans = images.shape[3] if images.ndim == 4 else 1
    flat = images.reshape(n_img, -1)  # (N, HW·C), no copy
    a = (lights.T @ lights).astype(np.float32)
    pinv = np.linalg.solve(a.astype(np.float64), lights.T.astype(np.float64)).astype(np.float32)  # (3, N)
    luma = LUMA if chans == 3 else np.ones(1, np.float32)
    normals = np.empty((len(idx_all), 3), np.float32)
    albedo = np.empty((len(idx_all), 3), np.float32)
    conf = np.empty(len(idx_all), np.float32)
    hw = flat.shape[1] // chans
    done = 0
    for p0 in range(0, hw, _CHUNK):
        p1 = min(p0 + _CHUNK, hw)
        sel = idx_all[(idx_all >= p0) & (idx_all < p1)]
        if len(sel) == 0:
            continue
        block = flat[:, p0 * chans:p1 * chans]
        g_c = (pinv @ block).reshape(3, p1 - p0, chans)  # per-channel scaled normals
        power = np.einsum("nk,nk->k", block, block).reshape(p1 - p0, chans).sum(1)
        local = sel - p0
        g_c = g_c[:, local]
        g = g_c @ luma  # (3, m)
        nrm = g / np.maximum(np.linalg.norm(g, axis=0), 1e-12)
        an = a @ nrm
        den = np.maximum((nrm * an).sum(0), 1e-12)
        rho = np.einsum("km,kmc->mc", an, g_c) / den[:, None]  # ρ_c = nᵀA g_c / nᵀA n
        explained = np.einsum("km,km->m", (a @ g_c.reshape(3, -1)), g_c.reshape(3, -1))
        explained = explained.reshape(-1, chans).sum(1)
        sl = slice(done, done + len(sel))
        normals[sl] = nrm.T
        albedo[sl] = rho if chans == 3 else np.repeat(rho, 3, axis=1)
        conf[sl] = _confidence_from(np.full(len(sel), float(n_img)), power[local] - explained, power[local],
                                    n_img, robust=False)
        done += len(sel)
    return normals, albedo, conf


def _near(images, idx, lights, positions, shape):
    """Pixels ``idx`` (:func:`_pixels`) and their lights: shared directions, or near lights'
    per-pixel directions with the measurements divided by the fall-off."""
    grey, colour = _pixels(images, idx)
    if positions is None:
        return grey, colour, lights
    here, falloff = point_light_field(positions, shape, idx)
    return grey / falloff, colour / falloff.T[..., None], here


def _assemble(shape, mask, idx, normals, albedo, confidence, dpi, attrs):
    h, w = shape
    n_img = np.zeros((h * w, 3), np.float32)
    n_img[:, 2] = 1.0  # off-mask pixels: a valid unit normal facing the viewer, confidence 0
    a_img = np.zeros((h * w, 3), np.float32)
    c_img = np.zeros(h * w, np.float32)
    n_img[idx] = normals
    a_img[idx] = np.clip(albedo, 0.0, 1.0)
    c_img[idx] = confidence
    # a pixel whose solve collapsed (all lights dark) has no direction: report it unsolved
    dead = np.zeros(h * w, bool)
    dead[idx] = ~np.isfinite(normals).all(1) | (np.linalg.norm(normals, axis=1) < 0.5)
    n_img[dead] = (0.0, 0.0, 1.0)
    c_img[dead] = 0.0
    return RGBNImage(albedo=a_img.reshape(h, w, 3), mask=mask, dpi=dpi, normals=n_img.reshape(h, w, 3),
                     confidence=c_img.reshape(h, w), attrs=attrs)


@_one_blas_thread
def least_squares_normals(images, directions=None, *, positions=None, mask=None, valid=None, dpi: float = 96.0,
                          progress: Callable[[float, str], None] | None = None) -> RGBNImage:
    """Lambertian photometric stereo by least squares (Woodham; thesis eq. 3.2).

    Parameters
    ----------
    images : (N, H, W) or (N, H, W, 3) float array
        Linear intensities, already divided by each light's intensity.
    directions : (N, 3) array
        Distant light directions (x right, y up, z towards the camera); normalised here.
    positions : (N, 3) array, optional
        Near point lights instead of ``directions``: positions in pixels, x right and y up from
        the image centre, z towards the camera (a dome of radius R: R × the unit directions of
        its ``.lp`` file). Each pixel then has its own light directions and each measurement is
        divided by its 1/r² fall-off (:func:`point_light_field`), relative to the image centre.
    mask : (H, W) bool, optional
        Pixels to solve (default all).
    valid : (N, H, W) bool, optional
        False marks measurements to ignore (saturated). With it each pixel gets its own normal
        equations; without it one pseudo-inverse serves every pixel.
    dpi : float
        Sampling density stored in the result.
    progress : callable(fraction, text), optional
        Progress report.

    Returns
    -------
    RGBNImage
        Unit normals (x right, y up, z to viewer), RGB albedo ρ_c (clipped to [0, 1]),
        confidence = 1 − relative residual (0 for a pixel with fewer than 3 valid lights), the mask.

    Notes
    -----
    Normals are solved on the luminance (BT.601 weights) of colour images, then the albedo of
    each channel by least squares with the normal fixed. The paper's ``g = ρ n`` is ``g`` here.

    References
    ----------
    Thesis §3.2, eq. 3.2. R. J. Woodham, "Photometric method for determining surface
    orientation from multiple images", Optical Engineering 19(1), 1980.

    Examples
    --------
    >>> import numpy as np
    >>> L = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8]])
    >>> n = np.array([0.0, 0.6, 0.8])
    >>> images = np.tile((0.5 * L @ n)[:, None, None], (1, 2, 2)).astype(np.float32)
    >>> out = least_squares_normals(images, L)
    >>> [round(float(v), 3) + 0.0 for v in out.normals[0, 0]], round(float(out.albedo[0, 0, 0]), 3)
    ([0.0, 0.6, 0.8], 0.5)
    """
    images, lights, mask, valid = _check_inputs(images, directions, mask, valid, positions)
    n_img, h, w = images.shape[:3]
    idx_all = np.flatnonzero(mask)
    if valid is None and positions is None:
        normals, albedo, conf = _least_squares_linear(images, lights, idx_all)
        if progress:
            progress(1.0, "least-squares normals")
    else:
        normals = np.empty((len(idx_all), 3), np.float32)
        albedo = np.empty((len(idx_all), 3), np.float32)
        conf = np.empty(len(idx_all), np.float32)
        for start in range(0, len(idx_all), _CHUNK):
            idx = idx_all[start:start + _CHUNK]
            grey, colour, here = _near(images, idx, lights, positions, (h, w))
            weights = (np.ones(grey.shape, np.float32) if valid is None
                       else np.ascontiguousarray(valid.reshape(n_img, -1)[:, idx].T, dtype=np.float32))
            g = _weighted_solve(grey, here, weights)
            nrm, _ = _unit(g)
            sl = slice(start, start + len(idx))
            normals[sl] = nrm
            albedo[sl] = _broadcast_rgb(_albedo_rgb(colour, here, nrm, weights))
            conf[sl] = _confidence(grey, _predict(g, here), weights, n_img, robust=False)
            if progress:
                progress(min(1.0, (start + len(idx)) / max(len(idx_all), 1)), "least-squares normals")
    return _assemble((h, w), mask, idx_all, normals, albedo, conf, dpi,
                     {"normal_solver": "least_squares", "n_lights": n_img, "near_lights": positions is not None})


@_one_blas_thread
def robust_normals(images, directions=None, *, positions=None, mask=None, valid=None, dpi: float = 96.0,
                   shadow_fraction: float = 0.2, highlight_fraction: float = 0.1,
                   iterations: int = 3, min_shading: float = 0.3, residual_cutoff: float = 2.0,
                   progress: Callable[[float, str], None] | None = None) -> RGBNImage:
    """Photometric stereo that rejects shadows and highlights per pixel (thesis §3.2, eq. 3.2).

    Parameters
    ----------
    images : (N, H, W) or (N, H, W, 3) float array
        Linear intensities, already divided by each light's intensity.
    directions : (N, 3) array
        Distant light directions (x right, y up, z towards the camera).
    positions : (N, 3) array, optional
        Near point lights instead of ``directions`` (see :func:`least_squares_normals`).
    mask : (H, W) bool, optional
        Pixels to solve (default all).
    valid : (N, H, W) bool, optional
        False marks measurements never to use (saturated pixels).
    dpi : float
        Sampling density stored in the result.
    shadow_fraction, highlight_fraction : float in [0, 1)
        Initial trimming: per pixel the darkest ``shadow_fraction`` and brightest
        ``highlight_fraction`` of its valid measurements are dropped before the first solve.
    iterations : int ≥ 0
        Re-weighting rounds after the trimmed solve.
    min_shading : float in [0, 1)
        A light is used only where the current normal sees it at ``l·n > min_shading``: near
        and beyond the terminator the Lambertian model fails first (attached shadow, and the
        non-Lambertian fall-off of real materials).
    residual_cutoff : float > 0
        Measurements whose residual exceeds this many RMS residuals of the pixel are dropped
        (specular highlights, cast shadows).
    progress : callable(fraction, text), optional
        Progress report.

    Returns
    -------
    RGBNImage
        Normals, RGB albedo (clipped to [0, 1]), confidence = support × (1 − relative residual)
        with support = clip((kept − 3) / max(3, N/4), 0, 1) (0 with 3 or fewer kept lights, full
        at 3 + max(3, N/4); so fewer than 4 images give confidence 0 everywhere), mask. ``attrs['mean_inliers']`` is the mean number of lights
        used per pixel.

    Notes
    -----
    Rank trimming gives a starting point that is already free of the worst outliers; the
    re-weighted solves then choose the lights by geometry and residual. Each round is one
    batched 3×3 solve over all pixels. A pixel left with fewer than 3 lights gets the
    trimmed-solve normal and confidence 0.

    References
    ----------
    Thesis §3.2 (robust least squares on the redundant flash images). Related: Wu et al.,
    "Robust photometric stereo via low-rank matrix completion and recovery", ACCV 2010;
    Mukaigawa et al., "Analysis of photometric factors based on photometric linearization",
    JOSA A 2007 (classification of shadows and highlights).

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> L = rng.normal(size=(40, 3)); L[:, 2] = np.abs(L[:, 2]) + 0.5
    >>> L /= np.linalg.norm(L, axis=1, keepdims=True)
    >>> n = np.array([0.3, -0.2, 0.93]); n /= np.linalg.norm(n)
    >>> I = 0.7 * np.clip(L @ n, 0, None); I[5] = 1.0  # a specular highlight
    >>> out = robust_normals(np.tile(I[:, None, None], (1, 2, 2)).astype(np.float32), L)
    >>> bool(np.degrees(np.arccos(np.clip(out.normals[0, 0] @ n, -1, 1))) < 0.5)
    True
    """
    images, lights, mask, valid = _check_inputs(images, directions, mask, valid, positions)
    for name, v in (("shadow_fraction", shadow_fraction), ("highlight_fraction", highlight_fraction)):
        if not 0.0 <= v < 1.0:
            raise ValueError(f"{name} must be in [0, 1), got {v}")
    if shadow_fraction + highlight_fraction >= 0.9:
        raise ValueError("shadow_fraction + highlight_fraction must leave at least 10% of the lights")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if not 0.0 <= min_shading < 1.0:
        raise ValueError(f"min_shading must be in [0, 1), got {min_shading}")
    if residual_cutoff <= 0:
        raise ValueError(f"residual_cutoff must be positive, got {residual_cutoff}")
    n_img, h, w = images.shape[:3]
    idx_all = np.flatnonzero(mask)
    normals = np.empty((len(idx_all), 3), np.float32)
    albedo = np.empty((len(idx_all), 3), np.float32)
    conf = np.empty(len(idx_all), np.float32)
    inliers = 0.0
    for start in range(0, len(idx_all), _CHUNK):
        idx = idx_all[start:start + _CHUNK]
        grey, colour, here = _near(images, idx, lights, positions, (h, w))
        ok = None if valid is None else np.ascontiguousarray(valid.reshape(n_img, -1)[:, idx].T)
        g, weights = _robust_block(grey, ok, here, shadow_fraction, highlight_fraction, iterations,
                                   min_shading, residual_cutoff)
        nrm, _ = _unit(g)
        sl = slice(start, start + len(idx))
        normals[sl] = nrm
        albedo[sl] = _broadcast_rgb(_albedo_rgb(colour, here, nrm, weights))
        conf[sl] = _confidence(grey, _predict(g, here), weights, n_img, robust=True)
        inliers += float(weights.sum())
        if progress:
            progress(min(1.0, (start + len(idx)) / max(len(idx_all), 1)), "robust normals")
    return _assemble((h, w), mask, idx_all, normals, albedo, conf, dpi,
                     {"normal_solver": "robust", "n_lights": n_img, "near_lights": positions is not None,
                      "mean_inliers": inliers / max(len(idx_all), 1)})


def _broadcast_rgb(albedo):
    return albedo if albedo.shape[1] == 3 else np.repeat(albedo, 3, axis=1)


def _robust_block(grey, ok, lights, lo, hi, iterations, min_shading, cutoff):
    """Trimmed solve then re-weighted rounds for one block of pixels (pixel-major (P, N) arrays).

    Returns g (P, 3) and the final weights (P, N).
    """
    p, n = grey.shape
    # per-pixel rank trimming: the k-th smallest valid intensities bound the kept band
    if ok is None:
        k_lo = int(np.floor(lo * n))
        k_hi = max(int(np.ceil((1.0 - hi) * n)) - 1, k_lo)
        part = np.partition(grey, (k_lo, k_hi), axis=1)
        v_lo, v_hi = part[:, k_lo:k_lo + 1], part[:, k_hi:k_hi + 1]
        del part
        weights = ((grey >= v_lo) & (grey <= v_hi)).astype(np.float32)
    else:
        n_ok = ok.sum(1)
        srt = np.sort(np.where(ok, grey, np.inf), axis=1)  # invalid sort to the end
        k_lo = np.floor(lo * n_ok).astype(int)
        k_hi = np.clip(np.maximum(np.ceil((1.0 - hi) * n_ok).astype(int) - 1, k_lo), 0, n - 1)
        v_lo = np.take_along_axis(srt, k_lo[:, None], 1)
        v_hi = np.take_along_axis(srt, k_hi[:, None], 1)
        del srt
        weights = (ok & (grey >= v_lo) & (grey <= v_hi)).astype(np.float32)
    g = _weighted_solve(grey, lights, weights)
    g_start = g
    cut2 = np.float32(cutoff * cutoff)
    for _ in range(iterations):
        rho = np.linalg.norm(g, axis=1)
        pred = _predict(g, lights)  # = rho · (l·n): the shading test below needs no second product
        r2 = grey - pred
        r2 *= r2
        dof = np.maximum(weights.sum(1) - 3.0, 1.0)
        scale2 = np.einsum("pn,pn->p", weights, r2) / dof
        # a floor on the scale: a near-perfect fit must not reject ordinary noise
        floor = 1e-3 * np.maximum(pred.max(1), 1e-6)
        scale2 = np.maximum(scale2, floor * floor).astype(np.float32)
        new = pred > (min_shading * rho)[:, None].astype(np.float32)
        new &= r2 < cut2 * scale2[:, None]
        if ok is not None:
            new &= ok
        enough = new.sum(1) >= 3
        # pixels left with < 3 lights keep their previous weights
        keep = weights[~enough]
        weights = new.astype(np.float32)
        weights[~enough] = keep
        g = _weighted_solve(grey, lights, weights)
    # where the re-weighted system is degenerate keep the trimmed solution
    bad = ~np.isfinite(g).all(1) | (weights.sum(1) < 3) | (np.linalg.norm(g, axis=1) == 0)
    if bad.any():
        g[bad] = g_start[bad]
        weights[bad] = 0.0
    return g, weights
