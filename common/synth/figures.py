"""Pictures of a synthetic wall: the painting, the crack pattern, fragments and their reassembly.

Used by ``tessera synth --pictures DIR`` and for ``docs/synth/``. 8-bit sRGB arrays (H, W, 3),
RGB order; :func:`save_png` writes them.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from common.synth.wall import Fragment, Wall


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear RGB in [0, 1] -> 8-bit sRGB."""
    x = np.clip(np.asarray(linear, np.float32), 0, 1)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.round(s * 255).astype(np.uint8)


def save_png(path, rgb8: np.ndarray) -> None:
    """Write an RGB uint8 picture as PNG (maximum compression)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(rgb8[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 9])


def _fit(img: np.ndarray, width: int) -> np.ndarray:
    if img.shape[1] == width:
        return img
    h = max(1, int(round(img.shape[0] * width / img.shape[1])))
    return cv2.resize(img, (width, h), interpolation=cv2.INTER_AREA if width < img.shape[1] else cv2.INTER_NEAREST)


def wall_picture(wall: Wall, width: int = 900) -> np.ndarray:
    """The painted wall before it broke (from the ground-truth preview)."""
    if "albedo" not in wall.preview:
        raise ValueError("wall has no preview painting")
    return _fit(to_srgb8(wall.preview["albedo"]), width)


def crack_picture(wall: Wall, width: int = 900, *, graph: bool = True) -> np.ndarray:
    """The crack pattern: delivered pieces in muted colours, missing pieces hatched grey, lost plaster
    black, cracks white; with ``graph`` the adjacency graph (centroid to centroid, line width ~ shared length)."""
    lab = wall.preview["labels"]
    ids = wall.preview["label_ids"]
    n = int(lab.max()) + 1
    rng = np.random.default_rng(0)
    colours = (rng.uniform(0.35, 0.85, (n, 3)) * 255).astype(np.uint8)
    missing = np.array([not i for i in ids] + [False] * max(0, n - len(ids)))[:n]
    img = np.zeros(lab.shape + (3,), np.uint8)
    inside = lab >= 0
    img[inside] = colours[lab[inside]]
    yy, xx = np.mgrid[0:lab.shape[0], 0:lab.shape[1]]
    hatch = ((xx + yy) // 3) % 2 == 0
    miss = inside & missing[np.clip(lab, 0, n - 1)]
    img[miss] = np.where(hatch[miss][:, None], 90, 60).astype(np.uint8)
    edge = np.zeros(lab.shape, bool)
    edge[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    edge[1:] |= lab[1:] != lab[:-1]
    img[edge & inside] = 255
    scale = width / lab.shape[1]
    img = _fit(img, width)
    if graph and wall.adjacency:
        g = wall.preview.get("grid_mm", 1.0)
        cent = {}
        for k, fid in enumerate(ids):
            if fid:
                r, c = np.nonzero(lab == k)
                if r.size:
                    cent[fid] = (c.mean() * scale, r.mean() * scale)
        for a, b, length in wall.adjacency:
            if a in cent and b in cent:
                p, q = cent[a], cent[b]
                cv2.line(img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), (20, 20, 20),
                         max(1, int(round(length / 25 * scale / g))), cv2.LINE_AA)
        for p in cent.values():
            cv2.circle(img, (int(p[0]), int(p[1])), max(2, int(2 * scale)), (0, 0, 0), -1, cv2.LINE_AA)
    return img


def _normal_rgb(n: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Normals as colours, exaggerated x4 in slope so fine relief shows."""
    t = n.copy()
    t[..., :2] *= 4.0
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    out = np.round((t * 0.5 + 0.5) * 255).astype(np.uint8)
    out[~mask] = 0
    return out


def _shaded(fr: Fragment) -> np.ndarray:
    """Albedo lit from the upper left at a grazing angle: shows relief and colour together."""
    n = fr.rgbn.normals
    light = np.array([-0.6, 0.6, 0.53])
    light /= np.linalg.norm(light)
    shade = np.clip((n @ light) / light[2], 0, 2.5)[..., None]
    out = to_srgb8(fr.rgbn.albedo * shade * 0.8)
    out[~fr.rgbn.mask] = 0
    return out


def fragment_sheet(fragments: list[Fragment], *, tile: int = 220, columns: int = 4) -> np.ndarray:
    """Fragments in their own frames: per fragment colour, raking light and normal map side by side."""
    rows = []
    cells = []
    for fr in fragments:
        if fr.rgbn is None:
            continue
        m = fr.rgbn.mask
        views = [to_srgb8(fr.rgbn.albedo), ]
        if fr.rgbn.normals is not None:
            views += [_shaded(fr), _normal_rgb(fr.rgbn.normals, m)]
        h, w = m.shape
        s = tile / max(h, w)
        views = [cv2.resize(v, (max(1, int(w * s)), max(1, int(h * s))), interpolation=cv2.INTER_AREA) for v in views]
        cell = np.full((tile + 18, (tile + 6) * len(views), 3), 255, np.uint8)
        for k, v in enumerate(views):
            cell[18:18 + v.shape[0], k * (tile + 6):k * (tile + 6) + v.shape[1]] = v
        label = fr.id.split("-")[-1] + (" spurious" if fr.spurious else "") + \
            "".join(f" {k}" for k in fr.notes if k in ("fade", "discolour"))
        cv2.putText(cell, label, (2, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        cells.append(cell)
    if not cells:
        raise ValueError("no fragment with an image to show")
    width = max(c.shape[1] for c in cells)
    cells = [np.pad(c, ((0, 0), (0, width - c.shape[1]), (0, 0)), constant_values=255) for c in cells]
    for i in range(0, len(cells), columns):
        row = cells[i:i + columns]
        row += [np.full_like(cells[0], 255)] * (columns - len(row))
        rows.append(np.hstack(row))
    return np.vstack(rows)


def thumbnail(fragment: Fragment, mm_per_px: float = 0.5) -> Fragment:
    """A copy of a fragment with its colour and mask resampled to ``mm_per_px`` (for pictures)."""
    from dataclasses import replace

    from common.rgbn.image import RGBNImage
    im = fragment.rgbn
    if im is None or im.pixel_mm >= mm_per_px:
        return replace(fragment)
    s = im.pixel_mm / mm_per_px
    size = (max(1, int(round(im.shape[1] * s))), max(1, int(round(im.shape[0] * s))))
    albedo = cv2.resize(im.albedo, size, interpolation=cv2.INTER_AREA)
    mask = cv2.resize(im.mask.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0.5
    # the pose maps pixel centres: keep pixel (0, 0) at the same place (x = col * pixel_mm)
    return replace(fragment, rgbn=RGBNImage(albedo=albedo, mask=mask, dpi=im.dpi * size[0] / im.shape[1]),
                   surface=None)


def reassembly_picture(wall: Wall, fragments: list[Fragment], *, mm_per_px: float = 0.5) -> np.ndarray:
    """Delivered fragments put back at their ground-truth poses (gaps = erosion and missing pieces)."""
    H, W = int(wall.height_mm / mm_per_px) + 1, int(wall.width_mm / mm_per_px) + 1
    canvas = np.full((H, W, 3), 30, np.uint8)
    for fr in fragments:
        if fr.pose is None or fr.rgbn is None:
            continue
        a = np.deg2rad(fr.pose[0])
        pm = fr.rgbn.pixel_mm
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        M = np.hstack([R * pm / mm_per_px, (np.array(fr.pose[1:]) / mm_per_px)[:, None]])
        img = to_srgb8(fr.rgbn.albedo)
        msk = fr.rgbn.mask.astype(np.uint8)
        warped = cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_AREA)
        wm = cv2.warpAffine(msk * 255, M, (W, H), flags=cv2.INTER_LINEAR) > 127
        canvas[wm] = warped[wm]
    return canvas


def collection_picture(pieces, dpi: float, *, mm_per_px: float = 0.5, title: str = "",
                       background: int = 24) -> np.ndarray:
    """Placed pieces of one object of a collection (:mod:`common.synth.stats`), alpha-composited
    at their true places, with a 5 cm scale bar -- e.g. a RePAIR object beside a synthetic wall."""
    placed = [p for p in pieces if p.matrix is not None]
    if not placed:
        raise ValueError("no placed piece to show")
    s = (25.4 / dpi) / mm_per_px
    boxes = []
    for p in placed:
        h, w = p.rgba.shape[:2]
        c = np.array([[0, 0, 1], [w, 0, 1], [0, h, 1], [w, h, 1]], float) @ p.matrix.T
        boxes.append(c)
    allc = np.vstack(boxes) * s
    x0, y0 = allc.min(axis=0) - 10
    x1, y1 = allc.max(axis=0) + 10
    W, H = int(x1 - x0), int(y1 - y0) + 40
    canvas = np.full((H, W, 3), background, np.float32)
    for p in placed:
        M = p.matrix * s
        M[:, 2] -= (x0, y0 - 30)
        rgba = p.rgba.astype(np.float32)
        warped = cv2.warpAffine(rgba, M, (W, H), flags=cv2.INTER_AREA, borderValue=0)
        a = warped[..., 3:] / 255.0
        canvas = canvas * (1 - a) + warped[..., :3] * a
    img = np.clip(canvas, 0, 255).astype(np.uint8)
    bar = int(round(50 / mm_per_px))
    cv2.rectangle(img, (10, H - 14), (10 + bar, H - 8), (235, 235, 235), -1)
    cv2.putText(img, "5 cm", (14 + bar, H - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (235, 235, 235), 1, cv2.LINE_AA)
    if title:
        cv2.putText(img, title, (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (235, 235, 235), 1, cv2.LINE_AA)
    return img
