"""Normal maps made by other tools: decoded, checked for being normal maps, convention told apart.

A normal map stores ``n`` as colour ``(n + 1) / 2`` (:mod:`common.rgbn.io`): OpenGL maps have
green = y up (Tessera's convention), DirectX maps green = y down. A photograph passed by mistake
decodes to vectors of every length pointing anywhere; a map in the other convention decodes to a
field that is not the gradient of any surface. :func:`normals_from_map` refuses the first and
measures the second (:func:`convention_curl`): the normals of a real surface give a gradient
field ``(p, q) = (-nx/nz, -ny/nz)`` whose curl ``dp/dy - dq/dx`` vanishes (Frankot & Chellappa
1988 integrate exactly this field); with y negated the curl becomes ``dp/dy + dq/dx``, as large
as the relief itself.
"""

from __future__ import annotations

import numpy as np

from common.imports.driver import ImportRefused

CONVENTIONS = ("opengl", "directx", "auto")
#: a mask pixel's decoded length must be within this of 1 to count as a unit vector
UNIT_TOLERANCE = 0.12
#: share of mask pixels that must be unit vectors, and that must face the viewer (nz > 0)
MIN_UNIT_SHARE = 0.85
MIN_FACING_SHARE = 0.9
#: curl ratio beyond which one convention is clearly the right one
CURL_RATIO = 2.5


def convention_curl(normals: np.ndarray, mask: np.ndarray, *, scale: int = 3) -> tuple[float, float]:
    """Median |curl| of the gradient field of ``normals`` read as OpenGL and as DirectX.

    Parameters
    ----------
    normals : (H, W, 3) float
        Vectors decoded in the OpenGL convention (x right, y up, z to the viewer).
    mask : (H, W) bool
    scale : int
        Half-size in pixels of the square over which the gradient field is averaged before the
        curl is taken (quantisation noise of 8-bit maps swamps a one-pixel curl).

    Returns
    -------
    curl_opengl, curl_directx : float
        Mean absolute curl (1/pixel; the top 1 % left out) over pixels whose whole neighbourhood is
        in the mask and faces the viewer (nz > 0.2); NaN when fewer than 100 such pixels. The right convention has the
        smaller one.

    References
    ----------
    R. T. Frankot, R. Chellappa, "A method for enforcing integrability in shape from shading
    algorithms", IEEE PAMI 10(4), 1988.
    """
    import cv2
    n = np.asarray(normals, np.float64)
    ok = np.asarray(mask, bool) & (n[..., 2] > 0.2)
    nz = np.where(ok, n[..., 2], 1.0)
    p = np.where(ok, -n[..., 0] / nz, 0.0)
    q = np.where(ok, -n[..., 1] / nz, 0.0)   # y up
    # average over (2k+1)^2 pixels inside the mask, then difference across 2k pixels: the curl over a
    # few pixels outgrows the quantisation noise of 8-bit maps (a 1-pixel curl is mostly noise)
    k = scale
    box = (2 * k + 1, 2 * k + 1)
    w = cv2.boxFilter(ok.astype(np.float64), -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT)
    full = w >= box[0] * box[1] - 0.5
    ps = cv2.boxFilter(p, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT) / np.maximum(w, 1)
    qs = cv2.boxFilter(q, -1, box, normalize=False, borderType=cv2.BORDER_CONSTANT) / np.maximum(w, 1)
    dp_drow = np.zeros_like(p)
    dq_dcol = np.zeros_like(q)
    dp_drow[k:-k] = (ps[2 * k:] - ps[:-2 * k]) / (2 * k)
    dq_dcol[:, k:-k] = (qs[:, 2 * k:] - qs[:, :-2 * k]) / (2 * k)
    inner = np.zeros_like(ok)
    inner[k:-k, k:-k] = (full[2 * k:, k:-k] & full[:-2 * k, k:-k] & full[k:-k, 2 * k:] & full[k:-k, :-2 * k])
    if inner.sum() < 100:
        return float("nan"), float("nan")
    # y up: d/dy = -d/drow
    gl = np.abs(-dp_drow - dq_dcol)[inner]
    dx = np.abs(-dp_drow + dq_dcol)[inner]
    return _trimmed_mean(gl), _trimmed_mean(dx)


def _trimmed_mean(a: np.ndarray) -> float:
    """Mean below the 99th percentile: the occasional crease or map seam does not decide."""
    return float(a[a <= np.percentile(a, 99)].mean())


def decode_normal_map(pixels: np.ndarray, full_scale: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Raw vectors ``2 v / full_scale - 1`` (float maps: the values) and the alpha mask (or None)."""
    arr = np.asarray(pixels)
    if arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ValueError(f"pixels must be (H, W, 3) or (H, W, 4), got shape {arr.shape}")
    alpha = arr[..., 3] > 0 if arr.shape[2] == 4 else None
    v = arr[..., :3].astype(np.float32)
    if full_scale != 1.0:
        v = v * np.float32(2.0 / full_scale) - np.float32(1.0)
    return v, alpha


def normals_from_map(pixels: np.ndarray, full_scale: float, *, convention: str = "opengl",
                     mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Unit normals and mask from a normal-map image, or a refusal saying why it is not one.

    Parameters
    ----------
    pixels : (H, W, 3) or (H, W, 4) array
        RGB(A) samples as stored (uint8, uint16, or float vectors with ``full_scale`` 1).
    full_scale : float
        255, 65535 or 1.0.
    convention : {'opengl', 'directx', 'auto'}
        Green = y up (OpenGL), y down (DirectX), or told from the data (:func:`convention_curl`).
    mask : (H, W) bool, optional
        Further restriction (e.g. the albedo's alpha).

    Returns
    -------
    normals : (H, W, 3) float32
        Unit vectors, x right, y up, z to the viewer; ``(0, 0, 1)`` outside the mask.
    mask : (H, W) bool
        Alpha > 0 (if any), decoded length within 0.5 of 1 (the black or white background of
        many maps is out), and ``mask``.
    info : dict
        ``convention`` used, ``curl_opengl``, ``curl_directx``, ``unit_share``, ``facing_share``.

    Raises
    ------
    ImportRefused
        Not a normal map (too few unit vectors, too many facing away: a photograph), nothing
        valid, or the declared convention contradicted by the data (its curl ``CURL_RATIO``
        times the other's), or ``auto`` unable to tell.
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    v, alpha = decode_normal_map(pixels, full_scale)
    length = np.sqrt(np.einsum("...i,...i->...", v, v))
    shown = np.ones(length.shape, bool) if alpha is None else alpha.copy()
    if mask is not None:
        shown &= np.asarray(mask, bool)
    valid = shown & np.isfinite(length) & (length > 0.5) & (length < 1.5)
    if valid.sum() < max(16, 0.01 * shown.sum()):
        raise ImportRefused("not a normal map: almost no pixel decodes to a unit vector "
                            f"({valid.sum()} of {shown.sum()} shown pixels)")
    unit_share = float((np.abs(length[valid] - 1.0) < UNIT_TOLERANCE).mean())
    facing_share = float((v[..., 2][valid] > 0).mean())
    if unit_share < MIN_UNIT_SHARE or facing_share < MIN_FACING_SHARE:
        raise ImportRefused(f"not a normal map (a photograph?): only {unit_share * 100:.0f} % of its pixels decode "
                            f"to unit vectors (a normal map: over {MIN_UNIT_SHARE * 100:.0f} %) and "
                            f"{facing_share * 100:.0f} % face the viewer (blue above half scale; a normal map: "
                            f"over {MIN_FACING_SHARE * 100:.0f} %)")
    normals = np.zeros_like(v)
    normals[..., 2] = 1.0
    normals[valid] = v[valid] / length[valid][:, None]
    c_gl, c_dx = convention_curl(normals, valid)
    info = {"curl_opengl": c_gl, "curl_directx": c_dx, "unit_share": unit_share, "facing_share": facing_share}
    clear = np.isfinite(c_gl) and max(c_gl, c_dx) > CURL_RATIO * min(c_gl, c_dx) and max(c_gl, c_dx) > 1e-3
    looks = ("opengl" if c_gl < c_dx else "directx") if clear else None
    if convention == "auto":
        if looks is None:
            raise ImportRefused(f"cannot tell OpenGL from DirectX (curl {c_gl:.2g} read as OpenGL, {c_dx:.2g} as "
                                "DirectX: too little relief); give --convention opengl or directx")
        convention = looks
    elif looks is not None and looks != convention:
        raise ImportRefused(f"declared {convention} but the map reads as {looks} (green = y "
                            f"{'up' if looks == 'opengl' else 'down'}): its normals are integrable only that way "
                            f"(curl {c_gl:.2g} as OpenGL, {c_dx:.2g} as DirectX); give --convention {looks}")
    if convention == "directx":
        normals[..., 1] = -normals[..., 1]
    info["convention"] = convention
    return normals, valid, info
