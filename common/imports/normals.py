"""Normal maps made by other tools: decoded, checked for being normal maps, convention checked.

A normal map stores ``n`` as colour ``(n + 1) / 2`` (:mod:`common.rgbn.io`): OpenGL maps have
green = y up (Tessera's convention), DirectX maps green = y down. The two tests are the ones
every reader of normal maps in Tessera uses: :func:`common.rgbn.io.check_normal_map` (a
photograph decodes to vectors of every length, many facing away) and
:func:`common.rgbn.io.detect_convention` (the normals of a real surface are integrable only in
their own convention: the curl of ``(p, q) = (-nx/nz, -ny/nz)`` vanishes; Frankot & Chellappa
1988). The importer adds its policy: a declared convention the data clearly contradicts is
refused, and ``auto`` refuses a map too flat to tell rather than guess.
"""

from __future__ import annotations

import numpy as np

from common.imports.driver import ImportRefused
from common.rgbn.io import check_normal_map, detect_convention

CONVENTIONS = ("opengl", "directx", "auto")
#: ratio of the two readings' curl from which a declared convention counts as contradicted
CURL_RATIO = 2.5
#: below this ratio ``auto`` cannot tell the conventions apart
UNDECIDED_RATIO = 1.5


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
        Green = y up (OpenGL), y down (DirectX), or told from the data
        (:func:`common.rgbn.io.detect_convention`).
    mask : (H, W) bool, optional
        Further restriction (e.g. the albedo's alpha).

    Returns
    -------
    normals : (H, W, 3) float32
        Unit vectors, x right, y up, z to the viewer; ``(0, 0, 1)`` outside the mask.
    mask : (H, W) bool
        Alpha > 0 (if any), not all-zero (the black background of many maps), decoded length
        within 0.5 of 1, and ``mask``.
    info : dict
        ``convention`` used; ``curl_opengl``, ``curl_directx`` and their ``ratio`` (the evidence).

    Raises
    ------
    ImportRefused
        Not a normal map (:func:`common.rgbn.io.check_normal_map`: too few unit vectors, too many
        facing away -- a photograph), nothing valid, a declared convention whose curl is
        ``CURL_RATIO`` times the other reading's, or ``auto`` on a map too flat to tell.

    Examples
    --------
    >>> px = np.zeros((40, 40, 3), np.uint8); px[..., 2] = 255; px[..., :2] = 128
    >>> n, m, info = normals_from_map(px, 255.0)
    >>> bool(m.all()), info["convention"]
    (True, 'opengl')
    """
    if convention not in CONVENTIONS:
        raise ValueError(f"convention must be one of {CONVENTIONS}, got {convention!r}")
    v, alpha = decode_normal_map(pixels, full_scale)
    length = np.sqrt(np.einsum("...i,...i->...", v, v))
    shown = np.any(np.asarray(pixels)[..., :3] != 0, axis=2)   # all-zero: background, not a vector
    if alpha is not None:
        shown &= alpha
    if mask is not None:
        shown &= np.asarray(mask, bool)
    valid = shown & np.isfinite(length) & (length > 0.5) & (length < 1.5)
    if valid.sum() < max(16, 0.01 * shown.sum()):
        raise ImportRefused("not a normal map: almost no pixel decodes to a unit vector "
                            f"({valid.sum()} of {shown.sum()} shown pixels)")
    try:
        check_normal_map(v, length, shown, name="it")
    except ValueError as exc:
        raise ImportRefused(str(exc)) from None
    normals = np.zeros_like(v)
    normals[..., 2] = 1.0
    normals[valid] = v[valid] / length[valid][:, None]
    looks, evidence = detect_convention(normals, valid)
    ratio = float(evidence.get("ratio") or 0.0)
    info = {"curl_opengl": evidence.get("curl_opengl"), "curl_directx": evidence.get("curl_directx"), "ratio": ratio}
    curls = (f"median curl {evidence.get('curl_opengl')} read as OpenGL, {evidence.get('curl_directx')} "
             "as DirectX")
    if convention == "auto":
        if ratio < UNDECIDED_RATIO:
            raise ImportRefused(f"cannot tell OpenGL from DirectX ({curls}: too little relief); "
                                "give --convention opengl or directx")
        convention = looks
    elif looks != convention and ratio >= CURL_RATIO:
        raise ImportRefused(f"declared {convention} but the map reads as {looks} (green = y "
                            f"{'up' if looks == 'opengl' else 'down'}): its normals are integrable only that way "
                            f"({curls}); give --convention {looks}")
    if convention == "directx":
        normals[..., 1] = -normals[..., 1]
    info["convention"] = convention
    return normals, valid, info
