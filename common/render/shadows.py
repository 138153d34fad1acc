"""Fast discontinuity shadows (§7.3.7, eqs. 7.9-7.11).

A depth discontinuity whose higher (occluding) side faces the light casts a shadow onto the
lower side, away from the light. Without depth, the shadow is drawn in image space:

* eq. 7.9  — the source strength ``s(p) = |d(p)| * max(0, d̂(p) . l̂)``: a discontinuity vector
  d (pointing towards the occluding side, length = strength) lit from the light's azimuth l̂;
* eq. 7.10 — the shadow ``S(p) = max_{0 <= t <= L} s(p + t l̂) (1 - t / L)``: each source is
  smeared away from the light over a length ``L = length_px``, fading linearly;
* eq. 7.11 — the shaded image is multiplied by ``1 - opacity * S``.

Discontinuities come from the flash capture's map (Raskar et al. 2004) when there is one, else
from the normals (steep walls: ``d = -(nx, ny)`` scaled by a smoothstep of ``1 - nz``) and from
the fragment outline (the fragment stands above the background, so its outline casts a drop
shadow on the page).
"""

from __future__ import annotations

import numpy as np

from common.render._util import as_light, smoothstep
from common.rgbn._filters import check_mask, gaussian_blur


def discontinuity_sources(normals: np.ndarray | None = None, *, mask: np.ndarray | None = None,
                          discontinuity: np.ndarray | None = None, steep_nz: float = 0.5,
                          outline: bool = True) -> np.ndarray:
    """Discontinuity vectors (H, W, 2), x right / y up, towards the occluding side (eq. 7.9 input)."""
    shape = next((np.shape(a)[:2] for a in (discontinuity, normals, mask) if a is not None), None)
    if shape is None:
        raise ValueError("discontinuity_sources needs normals, a discontinuity map or a mask")
    mask = check_mask(mask, shape)
    if discontinuity is not None:
        d = np.asarray(discontinuity, np.float32)
        if d.shape != tuple(shape) + (2,):
            raise ValueError(f"discontinuity must be {tuple(shape) + (2,)}, got {d.shape}")
        d = d.copy()
    else:
        d = np.zeros(tuple(shape) + (2,), np.float32)
        if normals is not None:
            n = np.asarray(normals, np.float32)
            steep = smoothstep(steep_nz, max(steep_nz - 0.3, 0.0), n[..., 2]) if steep_nz > 0 else 0.0
            nxy = np.hypot(n[..., 0], n[..., 1])
            scale = np.where((nxy > 1e-6) & mask, steep / np.maximum(nxy, 1e-6), 0.0)
            # a wall's normal points down-slope: the occluder is the other way
            d[..., 0] = -n[..., 0] * scale
            d[..., 1] = -n[..., 1] * scale
    if outline and not mask.all():
        m = gaussian_blur(mask.astype(np.float32), 1.0)
        gy, gx = np.gradient(m)
        edge = mask & (m < 0.99) | (~mask & (m > 0.01))
        g = np.hypot(gx, gy)
        # gradient of the mask points into the fragment, the occluding side; rows go down
        ox = np.where(edge, gx / np.maximum(g, 1e-6), 0.0)
        oy = np.where(edge, -gy / np.maximum(g, 1e-6), 0.0)
        stronger = edge & (np.hypot(d[..., 0], d[..., 1]) < 1.0)
        d[..., 0] = np.where(stronger, ox, d[..., 0])
        d[..., 1] = np.where(stronger, oy, d[..., 1])
    return d


def discontinuity_shadows(discontinuity: np.ndarray, light=(135.0, 45.0), *, length_px: float = 12.0,
                          softness_px: float = 1.0) -> np.ndarray:
    """Shadow strength S (H, W) in [0, 1] cast by depth discontinuities, eqs. 7.9-7.10.

    Parameters
    ----------
    discontinuity : (H, W, 2) float
        Vectors towards the occluding side, length = strength (see :func:`discontinuity_sources`).
    light : 3-vector or (azimuth_deg, elevation_deg)
        Light; only its azimuth in the image plane is used (a vertical light casts no shadow).
    length_px : float
        Shadow length L in pixels (a lower light or a higher step would give a longer shadow).
    softness_px : float
        Gaussian blur of the shadow edge.

    Returns
    -------
    (H, W) float32 in [0, 1]; multiply the shading by ``1 - opacity * S`` (eq. 7.11).

    References
    ----------
    Toler-Franklin 2011, §7.3.7, eqs. 7.9-7.11; Toler-Franklin et al., NPAR 2007, §4.4.

    Examples
    --------
    >>> d = np.zeros((5, 9, 2), np.float32); d[2, 4] = (1, 0)  # occluder on the right
    >>> s = discontinuity_shadows(d, (0.0, 30.0), length_px=3, softness_px=0)  # light from the right
    >>> [round(float(v), 2) for v in s[2]]
    [0.0, 0.0, 0.33, 0.67, 1.0, 0.0, 0.0, 0.0, 0.0]
    """
    d = np.asarray(discontinuity, np.float32)
    if d.ndim != 3 or d.shape[2] != 2:
        raise ValueError(f"discontinuity must be (H, W, 2), got shape {d.shape}")
    if not length_px >= 0:
        raise ValueError(f"length_px must be >= 0, got {length_px}")
    l = as_light(light)
    lxy = np.hypot(l[0], l[1])
    if lxy < 1e-6:
        return np.zeros(d.shape[:2], np.float32)
    ux, uy = l[0] / lxy, l[1] / lxy
    strength = np.hypot(d[..., 0], d[..., 1])
    # eq. 7.9: the occluding side must face the light
    facing = np.where(strength > 0, (d[..., 0] * ux + d[..., 1] * uy) / np.maximum(strength, 1e-12), 0.0)
    source = np.clip(strength, 0, 1) * np.maximum(facing, 0.0)
    source = source.astype(np.float32)
    # eq. 7.10: march away from the light; the shadow at p comes from sources towards the light
    shadow = source.copy()
    h, w = source.shape
    steps = int(np.ceil(length_px))
    for t in range(1, steps + 1):
        # source at p + t*u (u towards the light): rows go down, so y up is -row
        dc, dr = int(round(t * ux)), int(round(-t * uy))
        fade = np.float32(max(0.0, 1.0 - t / length_px)) if length_px > 0 else np.float32(0.0)
        if fade <= 0:
            break
        shifted = np.zeros_like(source)
        src_r = slice(max(dr, 0), h + min(dr, 0))
        dst_r = slice(max(-dr, 0), h + min(-dr, 0))
        src_c = slice(max(dc, 0), w + min(dc, 0))
        dst_c = slice(max(-dc, 0), w + min(-dc, 0))
        shifted[dst_r, dst_c] = source[src_r, src_c]
        np.maximum(shadow, shifted * fade, out=shadow)
    if softness_px > 0:
        shadow = gaussian_blur(shadow, softness_px)
    return np.clip(shadow, 0.0, 1.0)
