"""Normal-map descriptors: normal-z statistics, colour/normal variation (eq. 5.3) and normal
discontinuity statistics (§5.4.3, §5.4.4).

Normals follow the RGBN convention (x right, y up, z to the viewer). Every descriptor here is
invariant to rotating the fragment in the image plane: nz is unchanged by such a rotation, and
the (nx, ny) columns of the eq. 5.3 stack rotate orthogonally, which leaves its singular values
unchanged.
"""

from __future__ import annotations

import numpy as np

#: luminance weights (Rec. 709) for the colour column of the eq. 5.3 stack
LUMA = (0.2126, 0.7152, 0.0722)
_STACK = ("L", "nx", "ny", "nz")
#: per-pixel moment channels (means and second moments of the eq. 5.3 stack)
NORMAL_MOMENTS = _STACK + tuple(f"{a}*{b}" for i, a in enumerate(_STACK) for b in _STACK[i:])
#: neighbour |dnz| above this counts as a discontinuity (§5.4.4)
DISCONTINUITY_THRESHOLD = 0.46
#: added to both percentiles of the 80/50 ratio: about the |dnz| noise of a good normal map
RATIO_EPS = 1e-3
#: the moments use values clipped at this percentile
WINSOR_PERCENTILE = 99.0


def normal_channels(albedo, normals, centre=None) -> dict[str, np.ndarray]:
    """Per-pixel moment channels of luminance and normals (float32), centred on ``centre``
    (dict L, nx, ny, nz -> value, e.g. the fragment means; :func:`normal_from_moments` adds it
    back) so that small variances summed in float32 do not cancel."""
    a = np.asarray(albedo, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    c = {k: np.float32((centre or {}).get(k, 0.0)) for k in _STACK}
    cols = {"L": a[..., 0] * LUMA[0] + a[..., 1] * LUMA[1] + a[..., 2] * LUMA[2] - c["L"],
            "nx": n[..., 0] - c["nx"], "ny": n[..., 1] - c["ny"], "nz": n[..., 2] - c["nz"]}
    out = dict(cols)
    for i, p in enumerate(_STACK):
        for q in _STACK[i:]:
            out[f"{p}*{q}"] = cols[p] * cols[q]
    return out


def normal_from_moments(m, centre=None) -> dict[str, float]:
    """normal_z_mean, normal_z_variance and colour_normal_svd from weighted means of
    :data:`NORMAL_MOMENTS` (dict name -> mean) of channels centred on ``centre``."""
    cov = np.empty((4, 4))
    for i, p in enumerate(_STACK):
        for j, q in enumerate(_STACK):
            key = f"{p}*{q}" if i <= j else f"{q}*{p}"
            cov[i, j] = m[key] - m[p] * m[q]
    ev = np.linalg.eigvalsh(cov)
    # eigenvalues at float32 rounding level are zero: their square roots would add ~3e-4 each
    ev = np.where(ev > 1e-7 * max(ev.max(), 0.0), ev, 0.0)
    return {"normal_z_mean": float(m["nz"] + (centre or {}).get("nz", 0.0)), "normal_z_variance": float(max(cov[3, 3], 0.0)),
            "colour_normal_svd": float(np.sum(np.sqrt(np.clip(ev, 0.0, None))))}


def normal_statistics(albedo, normals, mask) -> dict[str, float]:
    """Normal-z mean and variance, and the colour/normal variation of eq. 5.3.

    The colour/normal variation is the sum of the singular values of the n × 4 stack of
    (luminance, nx, ny, nz) rows of the region's pixels, centred on their mean and divided by √n
    so that it does not grow with the region's size (it is the sum of the standard deviations
    along the stack's principal axes).

    Parameters
    ----------
    albedo : (H, W, 3) float
        Linear RGB albedo.
    normals : (H, W, 3) float
        Unit normals (x right, y up, z to viewer).
    mask : (H, W) bool or float
        Region (or weights in [0, 1]).

    Returns
    -------
    dict
        ``normal_z_mean``, ``normal_z_variance``, ``colour_normal_svd``; NaN for an empty region.

    References
    ----------
    Toler-Franklin 2011, §5.4.3 and eq. 5.3.

    Notes
    -----
    The thesis sums the singular values of the raw stack; the centring and 1/√n make the value a
    property of the surface, not of the patch's pixel count (the thesis' patches all have one size).

    Examples
    --------
    >>> n = np.zeros((8, 8, 3)); n[..., 2] = 1
    >>> s = normal_statistics(np.full((8, 8, 3), 0.5), n, np.ones((8, 8), bool))
    >>> s["normal_z_mean"], s["normal_z_variance"], round(s["colour_normal_svd"], 6)
    (1.0, 0.0, 0.0)
    """
    a = np.asarray(albedo, dtype=np.float32)
    n = np.asarray(normals, dtype=np.float32)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals must be (H, W, 3), got {n.shape}")
    if a.shape != n.shape:
        raise ValueError(f"albedo {a.shape} and normals {n.shape} must have the same shape")
    w = np.asarray(mask, dtype=np.float32)
    if w.shape != n.shape[:2]:
        raise ValueError(f"mask must be {n.shape[:2]}, got {w.shape}")
    tot = float(w.sum())
    if tot <= 0:
        return {"normal_z_mean": np.nan, "normal_z_variance": np.nan, "colour_normal_svd": np.nan}
    ch = normal_channels(a, n)
    centre = {k: float(np.sum(ch[k] * w, dtype=np.float64)) / tot for k in _STACK}
    ch = normal_channels(a, n, centre)  # centred: float32 products do not cancel
    return normal_from_moments({k: float(np.sum(v * w, dtype=np.float64)) / tot for k, v in ch.items()}, centre)


def neighbour_differences(nz, valid) -> np.ndarray:
    """Per-pixel normal-z difference to the neighbours, rotation-invariantly: the magnitude of
    the central-difference gradient of nz, in nz units per pixel (a straight step of height s
    between two pixels gives s/2 at each of them), at pixels whose 4 neighbours are valid."""
    nz = np.asarray(nz, dtype=np.float32)
    v = np.asarray(valid, dtype=bool)
    if nz.shape[0] < 3 or nz.shape[1] < 3:
        return np.zeros(0, np.float32)
    gx = 0.5 * (nz[1:-1, 2:] - nz[1:-1, :-2])
    gy = 0.5 * (nz[2:, 1:-1] - nz[:-2, 1:-1])
    ok = v[1:-1, 1:-1] & v[1:-1, 2:] & v[1:-1, :-2] & v[2:, 1:-1] & v[:-2, 1:-1]
    return np.sqrt(gx * gx + gy * gy)[ok]


def discontinuity_from_differences(d) -> dict[str, float]:
    """The four §5.4.4 statistics of a set of neighbour |dnz| values."""
    d = np.asarray(d, dtype=np.float32)
    nan = {"disc_ratio_80_50": np.nan, "disc_frac_046": np.nan, "disc_skewness": np.nan, "disc_kurtosis": np.nan}
    if d.size < 16:
        return nan
    n = d.size
    ks = [min(n - 1, int(round(q / 100 * (n - 1)))) for q in (50, 80, WINSOR_PERCENTILE)]
    part = np.partition(d, ks)  # nearest-rank percentiles, one partial sort
    p50, p80, p99 = (float(part[k]) for k in ks)
    dw = np.minimum(d, p99)  # moments of the winsorised values: a few crack pixels must not rule them
    mu = float(dw.mean(dtype=np.float64))
    z = dw - np.float32(mu)
    z2 = z * z
    var = float(z2.mean(dtype=np.float64))
    sd = np.sqrt(var)
    out = dict(nan)
    out["disc_frac_046"] = float(np.mean(d > DISCONTINUITY_THRESHOLD))
    out["disc_ratio_80_50"] = float((p80 + RATIO_EPS) / (p50 + RATIO_EPS))
    if sd > 1e-5 * mu + 1e-9:  # below: float rounding, not spread
        out["disc_skewness"] = float((z2 * z).mean(dtype=np.float64)) / sd ** 3
        out["disc_kurtosis"] = float((z2 * z2).mean(dtype=np.float64)) / var ** 2
    return out


def normal_discontinuity(nz, mask) -> dict[str, float]:
    """Statistics of the histogram of neighbouring normal-z differences (§5.4.4).

    Parameters
    ----------
    nz : (H, W) float
        z component of the unit normals.
    mask : (H, W) bool
        Pixels to use; a pair counts only when both of its pixels are in the mask.

    Returns
    -------
    dict
        ``disc_ratio_80_50`` (80th / 50th percentile of |dnz|), ``disc_frac_046`` (fraction of
        |dnz| above 0.46), ``disc_skewness`` and ``disc_kurtosis`` (third and fourth standardised
        moments, Gaussian kurtosis = 3). NaN where undefined (fewer than 16 pairs, or zero spread
        for the moments).

    References
    ----------
    Toler-Franklin 2011, §5.4.4 (normal discontinuity).

    Notes
    -----
    The ratio adds ``RATIO_EPS`` = 1e-3 to both percentiles so that a perfectly smooth map (median
    difference 0) has a defined ratio instead of a division by zero. The moments are taken of the
    differences clipped at their 99th percentile: unclipped, the handful of pixels on a crack
    dominate them and they change several-fold when the fragment is merely rotated on the
    scanner (measured in tests/features/test_table.py). Large steps are still counted by
    ``disc_frac_046``.

    Examples
    --------
    >>> nz = np.ones((16, 16)); nz[:, 8:] = 0.0      # a vertical wall: nz drops from 1 to 0
    >>> normal_discontinuity(nz, np.ones((16, 16), bool))["disc_frac_046"]   # 2 of 14 columns
    0.14285714285714285
    """
    nz = np.asarray(nz)
    if nz.ndim != 2:
        raise ValueError(f"nz must be 2-D, got shape {nz.shape}")
    if np.shape(mask) != nz.shape:
        raise ValueError(f"mask must be {nz.shape}, got {np.shape(mask)}")
    return discontinuity_from_differences(neighbour_differences(nz, mask))
