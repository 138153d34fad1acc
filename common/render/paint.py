"""Watercolour rendering of an RGBN image (§7.3.8).

The flat washes of a watercolour come from edge-preserving smoothing of the colour (the joint
colour+normal bilateral filter of eq. 7.2, or segment means); the pigment density varies with the
shading (relief from the normals), with a paper texture (low-frequency turbulence and grain), and
darkens at the edges of washes where pigment accumulates. Density is applied with the colour
modification model of Bousseau et al. (2006): ``C' = C - (C - C^2)(d - 1)``.
"""

from __future__ import annotations

import numpy as np

from common.render._util import as_light, dot_light
from common.rgbn._filters import check_mask, check_normals, gaussian_blur


def pigment_density(colour: np.ndarray, density: np.ndarray) -> np.ndarray:
    """Bousseau et al. 2006 density model: ``C' = C - (C - C^2)(d - 1)`` (d > 1 darkens)."""
    c = np.asarray(colour, np.float32)
    d = np.asarray(density, np.float32)
    if d.ndim == c.ndim - 1:
        d = d[..., None]
    return np.clip(c - (c - c * c) * (d - 1.0), 0.0, 1.0)


#: Side of the periodic paper sheet, pixels: the texture repeats every PAPER_PERIOD pixels, so any
#: window of a large image (a tile) gets the same paper as the whole image would.
PAPER_PERIOD = 1024


def paper_texture(shape, *, seed: int = 0, grain_px: float = 1.0, turbulence_px: float = 24.0,
                  origin=(0, 0)) -> np.ndarray:
    """Zero-mean paper texture in about [-1, 1]: fine grain plus low-frequency turbulence.

    The texture is one periodic sheet of ``PAPER_PERIOD`` pixels (blurred with wrap-around, so it
    tiles seamlessly) addressed by absolute position: ``origin`` (row, column) of the window in
    the whole image.
    """
    import cv2

    rng = np.random.default_rng(seed)
    p = PAPER_PERIOD

    def wrap(a, sigma):  # Gaussian blur of a periodic sheet (OpenCV has no wrap border for it)
        m = int(np.ceil(4 * sigma)) + 1
        return cv2.GaussianBlur(np.pad(a, m, mode="wrap"), (0, 0), sigma)[m:-m, m:-m]

    grain = wrap(rng.standard_normal((p, p)).astype(np.float32), grain_px)
    turb = wrap(rng.standard_normal((p, p)).astype(np.float32), turbulence_px)
    grain = (grain - grain.mean()) / max(float(grain.std()), 1e-6)
    turb = (turb - turb.mean()) / max(float(turb.std()), 1e-6)
    sheet = np.clip(0.35 * grain + 0.65 * turb, -3, 3) / 3.0
    h, w = shape
    rows = (np.arange(h) + int(origin[0])) % p
    cols = (np.arange(w) + int(origin[1])) % p
    return sheet[rows[:, None], cols[None, :]].astype(np.float32)


def watercolour(colour: np.ndarray, normals: np.ndarray | None = None, light=(135.0, 45.0), *,
                mask: np.ndarray | None = None, relief: float = 0.6, paper: float = 0.25,
                edge_darkening: float = 0.8, edge_px: float = 2.0, seed: int = 0, origin=(0, 0)) -> np.ndarray:
    """Watercolour look from flat colour washes, relief shading and paper texture (§7.3.8).

    Parameters
    ----------
    colour : (H, W, 3) float
        Display colour of the washes, ideally already flattened (bilateral filter or segment means).
    normals : (H, W, 3) float, optional
        Unit normals; the pigment density follows ``0.5 - n . l`` (shadowed slopes get more pigment).
    light : 3-vector or (azimuth_deg, elevation_deg)
        Light for the relief term.
    mask : (H, W) bool, optional
        The fragment (edge darkening also follows its outline).
    relief, paper, edge_darkening : float
        Strengths of the density terms (0 disables one).
    edge_px : float
        Width of the pigment accumulation at the edges of washes.
    seed : int
        Paper texture seed (the result is deterministic).
    origin : (int, int)
        Position (row, column) of this window in the whole image, for the paper texture.

    Returns
    -------
    (H, W, 3) float32 in [0, 1]

    References
    ----------
    A. Bousseau, M. Kaplan, J. Thollot, F. Sillion, "Interactive watercolor rendering with temporal
    coherence and abstraction", NPAR 2006; C. Curtis et al., "Computer-generated watercolor",
    SIGGRAPH 1997; Toler-Franklin 2011, §7.3.
    """
    colour = np.asarray(colour, np.float32)
    if colour.ndim != 3 or colour.shape[2] != 3:
        raise ValueError(f"colour must be (H, W, 3), got shape {colour.shape}")
    shape = colour.shape[:2]
    mask = check_mask(mask, shape)
    for name, value in (("relief", relief), ("paper", paper), ("edge_darkening", edge_darkening)):
        if value < 0:
            raise ValueError(f"{name} must be >= 0, got {value}")
    density = np.ones(shape, np.float32)
    if normals is not None and relief > 0:
        normals = check_normals(normals)
        density += np.float32(relief) * (0.5 - np.clip(dot_light(normals, as_light(light)), 0.0, 1.0))
    if paper > 0:
        density += np.float32(paper) * paper_texture(shape, seed=seed, origin=origin)
    if edge_darkening > 0:
        # pigment gathers where the wash changes: the colour gradient after a small blur
        lum = colour @ np.array([0.299, 0.587, 0.114], np.float32)
        lum = np.where(mask, lum, 1.0).astype(np.float32)
        soft = gaussian_blur(lum, edge_px)
        gy, gx = np.gradient(soft)
        edges = np.clip(np.hypot(gx, gy) * (4.0 * edge_px), 0.0, 1.0)
        density += np.float32(edge_darkening) * edges
    return pigment_density(colour, density)
