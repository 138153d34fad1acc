"""Generated test fragments for the feature tests: an irregular plaster fragment with painted
colour regions, brush-stroke relief and a crack, plus the rotation and noise the invariance tests
apply to it. Everything is drawn from physical coordinates (mm), so the ground truth is known."""

from __future__ import annotations

import cv2
import numpy as np

from common.rgbn.image import RGBNImage


def textured_fragment(*, dpi=150.0, size_mm=60.0, seed=0, stroke_period_mm=3.0, stroke_angle_deg=30.0,
                      stroke_amp_mm=0.06, crack=True, bumps=True, height=True,
                      canvas=1.6) -> RGBNImage:
    """An irregular fragment (radius ~ size/2 modulated by low harmonics) in a square canvas of
    ``canvas * size_mm`` (1.6: room to rotate it). Returns linear albedo, mask, normals (x right, y up, z out) and a height map."""
    rng = np.random.default_rng(seed)
    px = 25.4 / dpi
    n = int(np.ceil(size_mm * canvas / px))
    c = (n - 1) / 2
    yy, xx = np.mgrid[:n, :n].astype(np.float64)
    x, y = (xx - c) * px, (yy - c) * px              # mm, y down
    r, t = np.hypot(x, y), np.arctan2(y, x)
    radius = size_mm / 2 * (1 + sum(0.12 / k * np.cos(k * t + rng.uniform(0, 2 * np.pi)) for k in (2, 3, 5)))
    mask = r < radius
    # relief: brush strokes along stroke_angle, a few bumps, a crack (a narrow V groove)
    a = np.radians(stroke_angle_deg)
    u = x * np.cos(a) + y * np.sin(a)                # across the strokes
    h = stroke_amp_mm * np.sin(2 * np.pi * u / stroke_period_mm)
    for _ in range(6 if bumps else 0):
        bx, by = rng.uniform(-size_mm / 3, size_mm / 3, 2)
        h += 0.2 * np.exp(-((x - bx) ** 2 + (y - by) ** 2) / (2 * 3.0 ** 2))
    dist_crack = np.abs(0.6 * x - 0.8 * y - 3.0)
    pits = np.zeros_like(h)
    if crack:
        h -= np.clip(0.25 - dist_crack, 0, None) * 1.2
        for _ in range(25):  # eroded pits: small dark dents
            bx, by = rng.uniform(-size_mm / 2, size_mm / 2, 2)
            pr = rng.uniform(0.4, 0.9)
            pit = np.clip(1 - ((x - bx) ** 2 + (y - by) ** 2) / pr ** 2, 0, None)
            h -= 0.4 * pr * pit
            pits = np.maximum(pits, pit)
    hy_row, hx_col = np.gradient(h, px)
    nrm = np.stack([-hx_col, hy_row, np.ones_like(h)], axis=-1)  # y up: d/dy_up = -d/drow
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    # paint: two colour regions, soft boundary, fine pigment texture, darker crack
    region = 1 / (1 + np.exp(-(x + 0.5 * y) / 2.0))
    base = np.array([0.55, 0.25, 0.15]) * region[..., None] + np.array([0.7, 0.65, 0.5]) * (1 - region[..., None])
    texture = 1 + 0.05 * cv2.GaussianBlur(rng.standard_normal((n, n)), (0, 0), 1.5)[..., None]
    albedo = base * texture
    if crack:
        albedo *= (1 - 0.6 * np.exp(-dist_crack ** 2 / (2 * 0.15 ** 2)))[..., None]
        albedo *= (1 - 0.5 * pits)[..., None]
    albedo = np.clip(albedo, 0, 1)
    albedo[~mask] = 0.05
    nrm[~mask] = (0, 0, 1)
    hmap = np.where(mask, 10.0 + h, np.nan) if height else None
    return RGBNImage(albedo.astype(np.float32), mask, dpi, normals=nrm.astype(np.float32), height_mm=hmap)


def rotate_rgbn(image: RGBNImage, angle_deg: float) -> RGBNImage:
    """The same fragment turned ``angle_deg`` counter-clockwise on the screen about the canvas
    centre: every channel resampled, and the normals' (x, y) rotated with it."""
    h, w = image.shape
    R = cv2.getRotationMatrix2D(((w - 1) / 2, (h - 1) / 2), angle_deg, 1.0)

    def warp(a, interp=cv2.INTER_LINEAR):
        return cv2.warpAffine(np.ascontiguousarray(a, dtype=np.float32), R, (w, h), flags=interp,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    mask = warp(image.mask.astype(np.float32)) > 0.5
    albedo = np.dstack([warp(image.albedo[..., k]) for k in range(3)])
    n = np.dstack([warp(image.normals[..., k]) for k in range(3)]) if image.normals is not None else None
    if n is not None:
        ca, sa = np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))
        nx, ny = n[..., 0].copy(), n[..., 1].copy()
        # counter-clockwise on screen = counter-clockwise in the y-up normal frame
        n[..., 0], n[..., 1] = ca * nx - sa * ny, sa * nx + ca * ny
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        n[~mask] = (0, 0, 1)
    hm = None
    if image.height_mm is not None:
        hm = warp(np.nan_to_num(image.height_mm, nan=0.0))
        hm[~mask] = np.nan
    return RGBNImage(albedo, mask, image.dpi, normals=n, height_mm=hm)


def add_scanner_noise(image: RGBNImage, *, albedo_sigma=0.01, normal_sigma=0.01, seed=1) -> RGBNImage:
    """Gaussian noise on the albedo and on the normals' tilt (x, y; then renormalised)."""
    rng = np.random.default_rng(seed)
    albedo = np.clip(image.albedo + rng.normal(0, albedo_sigma, image.albedo.shape), 0, 1)
    n = None
    if image.normals is not None:
        n = image.normals.copy()
        n[..., :2] += rng.normal(0, normal_sigma, n[..., :2].shape)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return RGBNImage(albedo, image.mask, image.dpi, normals=n, height_mm=image.height_mm)


def match_patches(ref_table, other_table, transform, *, max_mm=2.0):
    """Pairs (i, j) of patches of the same kind whose centres coincide after mapping the other
    table's centres through ``transform`` (a callable on (N, 2) mm arrays) into ref's frame."""
    pairs = []
    mapped = transform(other_table.patch_centers_mm)
    for i in range(ref_table.n_patches):
        same = np.flatnonzero(other_table.patch_kind == ref_table.patch_kind[i])
        if not same.size:
            continue
        d = np.linalg.norm(mapped[same] - ref_table.patch_centers_mm[i], axis=1)
        if d.min() <= max_mm:
            pairs.append((i, int(same[np.argmin(d)])))
    return pairs


def rotation_back(image_shape, pixel_mm, angle_deg):
    """Map points (mm) of the rotated image back into the original frame."""
    h, w = image_shape
    c = np.array([(w - 1) / 2, (h - 1) / 2]) * pixel_mm
    a = np.radians(angle_deg)
    # cv2 rotates content by +angle CCW on screen: in (x right, y down) that is R(-angle)
    Rinv = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])

    def f(p):
        return (np.asarray(p) - c) @ Rinv.T + c
    return f
