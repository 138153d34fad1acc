"""Deterioration of a broken fragment: edge erosion, worn edges, pits, cracks, fading, discolouration.

These act on one fragment in its own frame after the break, so unlike the wall layers they
differ between neighbours: eroded edges no longer touch everywhere, and a faded or discoloured
fragment no longer shares its neighbour's colours (thesis Fig. 1.2).
"""

from __future__ import annotations

import cv2
import numpy as np

from common.synth.noise import FractalField

PLASTER = np.array([0.70, 0.66, 0.58], np.float32)  # exposed lime plaster under lost paint


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of a boolean mask (all False if empty)."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, bool)
    return lab == (1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA])))


def inner_distance_mm(mask: np.ndarray, pixel_mm: float) -> np.ndarray:
    """Distance (mm) from each mask pixel to the nearest pixel outside the mask."""
    m = np.pad(mask.astype(np.uint8), 1)
    return cv2.distanceTransform(m, cv2.DIST_L2, 5)[1:-1, 1:-1] * np.float32(pixel_mm)


def erode_edges(mask: np.ndarray, pixel_mm: float, rng: np.random.Generator, *, depth_mm: float = 0.8,
                chips: float = 0.2) -> np.ndarray:
    """Erode a fragment's broken edges by a depth that varies along the contour.

    Parameters
    ----------
    mask : (H, W) bool
        The freshly broken fragment.
    pixel_mm : float
        Pixel size.
    rng : numpy.random.Generator
    depth_mm : float
        Mean erosion depth; it varies between about 0 and 2.5x this along the edge.
    chips : float
        Expected number of chipped bites (small ellipses) per cm of contour.

    Returns
    -------
    (H, W) bool
        The eroded fragment (largest component).
    """
    if depth_mm < 0:
        raise ValueError(f"depth_mm must be >= 0, got {depth_mm}")
    if depth_mm == 0 and chips == 0:
        return mask.copy()
    G = np.array([[pixel_mm, 0.0, 0.0], [0.0, pixel_mm, 0.0]])
    vary = FractalField(rng, 8.0, octaves=4, persistence=0.6, amplitude=0.8).grid(G, mask.shape)
    dist = inner_distance_mm(mask, pixel_mm)
    # log-normal depth with median depth_mm along this fragment's edge
    edge = mask & (dist < 3 * depth_mm + 2 * pixel_mm)
    vary -= np.median(vary[edge]) if edge.any() else 0.0
    depth = np.float32(depth_mm) * np.exp(vary)
    out = mask & (dist > depth)
    # chipped bites: discs centred on the edge
    edge = np.argwhere(mask & (dist <= 1.5 * pixel_mm))
    if len(edge) and chips > 0:
        n = rng.poisson(chips * len(edge) * pixel_mm / 10.0)
        for r, c in edge[rng.integers(0, len(edge), n)]:
            axes = (max(1, int(round(rng.uniform(0.4, 1.8) / pixel_mm))),
                    max(1, int(round(rng.uniform(0.2, 0.9) / pixel_mm))))
            cv2.ellipse(out.view(np.uint8), (int(c), int(r)), axes, float(rng.uniform(0, 180)), 0, 360, 0, -1)
    return largest_component(out)


def wear_edges(height_mm: np.ndarray, mask: np.ndarray, pixel_mm: float, *, radius_mm: float = 0.8) -> np.ndarray:
    """Round off a fragment's edges: the face drops quadratically within ``radius_mm`` of the contour."""
    dist = inner_distance_mm(mask, pixel_mm)
    drop = np.where(mask & (dist < radius_mm), radius_mm * 0.5 * (1 - dist / radius_mm) ** 2, 0.0)
    return (height_mm - drop).astype(np.float32)


def pit_surface(height_mm: np.ndarray, albedo: np.ndarray, mask: np.ndarray, pixel_mm: float,
                rng: np.random.Generator, *, per_cm2: float = 0.15) -> None:
    """Add pits in place: small bowls where plaster and paint have spalled (paint shows plaster)."""
    cand = np.argwhere(mask)
    if not len(cand):
        return
    n = rng.poisson(per_cm2 * len(cand) * pixel_mm ** 2 / 100.0)
    for r, c in cand[rng.integers(0, len(cand), n)]:
        rad_mm = rng.uniform(0.2, 1.2)
        rp = int(np.ceil(rad_mm / pixel_mm)) + 1
        r0, r1, c0, c1 = max(r - rp, 0), min(r + rp + 1, mask.shape[0]), max(c - rp, 0), min(c + rp + 1, mask.shape[1])
        yy, xx = np.mgrid[r0:r1, c0:c1]
        d2 = ((yy - r) ** 2 + (xx - c) ** 2) * pixel_mm ** 2 / rad_mm ** 2
        bowl = np.clip(1.0 - d2, 0.0, None)
        height_mm[r0:r1, c0:c1] -= rng.uniform(0.1, 0.5) * rad_mm * bowl
        a = albedo[r0:r1, c0:c1]
        w = (bowl > 0)[..., None] * rng.uniform(0.5, 1.0)
        a[:] = a * (1 - w) + PLASTER * w


def crack_surface(height_mm: np.ndarray, albedo: np.ndarray, mask: np.ndarray, pixel_mm: float,
                  rng: np.random.Generator, *, per_cm2: float = 0.03) -> None:
    """Add hairline cracks in place: random walks, narrow grooves, darkened (dirt in the crack)."""
    cand = np.argwhere(mask)
    if not len(cand):
        return
    n = rng.poisson(per_cm2 * len(cand) * pixel_mm ** 2 / 100.0)
    if n == 0:
        return
    lines = np.zeros(mask.shape, np.uint8)
    for r, c in cand[rng.integers(0, len(cand), n)]:
        steps = rng.integers(10, 40)
        ang = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.35, steps))
        step_px = 1.0 / pixel_mm  # 1 mm steps
        pts = np.column_stack([c + np.cumsum(np.cos(ang)) * step_px, r + np.cumsum(np.sin(ang)) * step_px])
        cv2.polylines(lines, [np.round(pts * 16).astype(np.int32).reshape(-1, 1, 2)], False, 255, 1,
                      cv2.LINE_AA, shift=4)
    sigma = max(0.08 / pixel_mm, 0.5)
    g = cv2.GaussianBlur(lines.astype(np.float32) / 255.0, (0, 0), sigma)
    g /= max(g.max(), 1e-6)
    height_mm -= 0.15 * g
    albedo *= (1.0 - 0.35 * g)[..., None]


def fade(albedo: np.ndarray, amount: float) -> np.ndarray:
    """Fade paint towards the plaster white by ``amount`` in [0, 1] (pigment loss, weathering)."""
    if not 0 <= amount <= 1:
        raise ValueError(f"amount must be in [0, 1], got {amount}")
    return (albedo * (1 - amount) + np.float32(amount) * np.array([0.78, 0.75, 0.68], np.float32)).astype(np.float32)


DISCOLOURATIONS = {
    "burial brown": (0.95, 0.80, 0.58),
    "soot": (0.55, 0.53, 0.50),
    "lime crust": (1.15, 1.15, 1.12),
    "iron stain": (1.0, 0.72, 0.55),
}


def discolour(albedo: np.ndarray, kind: str, strength: float = 1.0) -> np.ndarray:
    """Tint a fragment (burial soil, fire, lime crust, iron): multiplies albedo by a colour."""
    if kind not in DISCOLOURATIONS:
        raise ValueError(f"kind must be one of {sorted(DISCOLOURATIONS)}, got {kind!r}")
    tint = 1.0 + strength * (np.array(DISCOLOURATIONS[kind], np.float32) - 1.0)
    return np.clip(albedo * tint, 0.0, 1.0).astype(np.float32)
