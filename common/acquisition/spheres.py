"""Light calibration from spheres in the frame (thesis §3.2).

A hand-held flash capture puts a mirror sphere and a diffuse sphere beside the object. With an
orthographic camera looking down −z (view vector v = (0, 0, 1) towards the camera):

* the **mirror sphere** shows each flash as a highlight where the sphere normal bisects view and
  light, so the light is the view vector reflected about that normal,
  ``l = 2 (n·v) n − v``;
* the **diffuse sphere** (Lambertian, known normals) gives each flash's relative intensity (and
  colour) by a one-parameter fit ``I = e · max(0, n·l)`` over the sphere's pixels.

Circles are ``(cx, cy, r)`` in pixels: ``cx`` the column, ``cy`` the row of the centre (row 0 at
the top), ``r`` the radius. Sphere normals use the project convention (x right, y up, z to the
viewer).
"""

from __future__ import annotations

import cv2
import numpy as np


def _check_circle(circle, shape=None):
    c = np.asarray(circle, dtype=np.float64).ravel()
    if c.shape != (3,) or not np.all(np.isfinite(c)) or c[2] <= 1.0:
        raise ValueError(f"circle must be (cx, cy, r) in pixels with r > 1, got {circle!r}")
    if shape is not None:
        h, w = shape
        if not (0 <= c[0] < w and 0 <= c[1] < h):
            raise ValueError(f"circle centre ({c[0]:.1f}, {c[1]:.1f}) lies outside the {w}x{h} image")
    return c


def fit_circle(points) -> np.ndarray:
    """Least-squares (Kåsa) circle through points ``(x, y)``: returns ``(cx, cy, r)``.

    References
    ----------
    I. Kåsa, "A circle fitting procedure and its error analysis", IEEE Trans. Instrum. Meas.
    25(1), 1976.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
        raise ValueError(f"points must be (K, 2) with K >= 3, got {p.shape}")
    x, y = p[:, 0], p[:, 1]
    a = np.column_stack([x, y, np.ones_like(x)])
    b = x * x + y * y
    sol, _, rank, _ = np.linalg.lstsq(a, b, rcond=None)
    if rank < 3:
        raise ValueError("points are collinear: no circle fits them")
    cx, cy = sol[0] / 2, sol[1] / 2
    r2 = sol[2] + cx * cx + cy * cy
    if not r2 > 0:
        raise ValueError("points are collinear: no circle fits them")
    return np.array([cx, cy, np.sqrt(r2)])


def find_sphere(image, *, radius_range: tuple[float, float] | None = None) -> np.ndarray:
    """Find a sphere's outline circle in a mask or an image.

    Parameters
    ----------
    image : (H, W) bool mask, or (H, W) / (H, W, 3) image
        A mask of the sphere (the largest connected region is used and a circle fitted to its
        boundary), or an image in which the strongest circle is found (Hough transform; for a
        flash capture pass the per-pixel median over the images, which shows a mirror
        sphere's rim without the moving highlights).
    radius_range : (r_min, r_max), optional
        Radii in pixels to search in an image (default 5% … 50% of the smaller side).

    Returns
    -------
    (3,) array
        ``(cx, cy, r)``: centre column, centre row, radius in pixels.

    Raises
    ------
    ValueError
        If the mask is empty or no circle is found.
    """
    arr = np.asarray(image)
    if arr.ndim == 3:
        if arr.shape[2] != 3:
            raise ValueError(f"image must be (H, W) or (H, W, 3), got {arr.shape}")
        arr = arr.astype(np.float32) @ np.array([0.2989, 0.5870, 0.1140], np.float32)
    if arr.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got {arr.shape}")
    if arr.dtype == bool:
        return _circle_from_mask(arr)
    return _hough_circles(arr, radius_range)[0]


def _hough_circles(arr, radius_range):
    """Circles (K, 3) found by the Hough transform, strongest first; ValueError if none."""
    h, w = arr.shape
    r_min, r_max = radius_range or (0.05 * min(h, w), 0.5 * min(h, w))
    if not 1 <= r_min < r_max:
        raise ValueError(f"radius_range must be (r_min, r_max) with 1 <= r_min < r_max, got {radius_range}")
    u8 = _stretch(arr)
    circles = cv2.HoughCircles(u8, cv2.HOUGH_GRADIENT, dp=1, minDist=r_min, param1=60, param2=30,
                               minRadius=int(r_min), maxRadius=int(np.ceil(r_max)))
    if circles is None:
        raise ValueError("no sphere outline found in the image; give the circle or a mask")
    ex, ey = _edge_pixels(u8)
    return np.array([_refine_circle(c, ex, ey) for c in circles[0][:16].astype(np.float64)])


def _stretch(arr):
    # a log stretch lifts the dark rim of a mirror sphere against a dark background, even
    # beside a bright diffuse sphere
    a = arr.astype(np.float32)
    a = np.log(np.clip(a, 0, None) + 1e-3 * max(float(a.max()), 1e-12))
    lo, hi = np.percentile(a, [1, 99.5])
    u8 = np.clip((a - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    return cv2.GaussianBlur(u8, (0, 0), 2)


def _edge_pixels(u8):
    ey, ex = np.nonzero(cv2.Canny(u8, 30, 60))
    return ex, ey


def _refine_circle(circle, ex, ey):
    """Sub-pixel circle: Kåsa fit to the edge pixels near a Hough circle (two passes)."""
    c = np.asarray(circle, np.float64)
    for band in (max(2.0, 0.05 * c[2]), 1.5):
        d = np.abs(np.hypot(ex - c[0], ey - c[1]) - c[2])
        near = d < band
        if near.sum() < 20:
            break
        c = fit_circle(np.column_stack([ex[near], ey[near]]))
    return c


def find_calibration_spheres(images, *, radius_range: tuple[float, float] | None = None,
                             candidates: int = 8) -> tuple[np.ndarray, np.ndarray | None]:
    """Find the mirror sphere and the diffuse sphere in a flash capture.

    Circles are proposed by a Hough transform of the median image, then told apart by how
    they respond to the moving flash: on a **mirror** sphere each flash lights a small spot
    (high peak over the median, few bright pixels); a **diffuse** sphere is Lambertian, so each
    image of it is fitted well by ``I = n · s`` with the sphere's own normals (R² close to 1).

    Parameters
    ----------
    images : (N, H, W) or (N, H, W, 3) array
        The flash images.
    radius_range : (r_min, r_max), optional
        Sphere radii to search, in pixels.
    candidates : int
        Hough circles examined (strongest first).

    Returns
    -------
    mirror : (3,) array
        ``(cx, cy, r)`` of the mirror sphere.
    diffuse : (3,) array or None
        ``(cx, cy, r)`` of the diffuse sphere, or None when no circle behaves like one
        (R² < 0.9).

    Raises
    ------
    ValueError
        If no circle behaves like a mirror sphere.
    """
    grey = _grey(images)
    if len(grey) < 2:
        raise ValueError("images: at least 2 flash images are needed to tell the spheres apart")
    circles = _hough_circles(np.median(grey, axis=0), radius_range)[:max(1, int(candidates))]
    shape = grey.shape[1:]
    mirror_score, lambert_r2 = [], []
    for c in circles:
        normals, inside = sphere_normals(shape, c, shrink=0.9)
        if inside.sum() < 20:
            mirror_score.append(0.0)
            lambert_r2.append(0.0)
            continue
        vals = grey[:, inside]  # (N, P)
        top, med = vals.max(1), np.median(vals, axis=1)
        contrast = (top - med) / np.maximum(top, 1e-12)
        spot = (vals > (med + 0.5 * (top - med))[:, None]).mean(1)
        mirror_score.append(float(np.median(contrast * (1.0 - spot))))
        nv = normals[inside]
        r2 = []
        for v in vals:  # per image: Lambertian fit on the lit side (two passes to settle the side)
            lit = v > 0.1 * max(float(v.max()), 1e-12)
            for _ in range(2):
                if lit.sum() < 10:
                    break
                s_, *_ = np.linalg.lstsq(nv[lit], v[lit], rcond=None)
                lit = nv @ s_ > 0.05 * np.linalg.norm(s_)
            if lit.sum() < 10:
                r2.append(0.0)
                continue
            pred = np.clip(nv @ s_, 0, None)
            r2.append(1.0 - np.sum((v - pred) ** 2) / max(float(np.sum((v - v.mean()) ** 2)), 1e-12))
        lambert_r2.append(float(np.median(r2)))
    # Hough order is vote order: the first circle that behaves like each sphere is taken
    mirrors = [k for k in range(len(circles)) if mirror_score[k] >= 0.5 and lambert_r2[k] < 0.9]
    if not mirrors:
        raise ValueError("no mirror sphere found in the images; give its circle or a mask")
    mirror = circles[mirrors[0]]
    diffuse = None
    for k in range(len(circles)):
        apart = np.hypot(*(circles[k][:2] - mirror[:2])) > circles[k][2] + 0.5 * mirror[2]
        if apart and lambert_r2[k] >= 0.9:
            # in the median image the diffuse sphere's shadowed side fades into the table; in
            # the max composite every side is lit: refine its outline there
            diffuse = _refine_circle(circles[k], *_edge_pixels(_stretch(grey.max(axis=0))))
            break
    return mirror, diffuse


def _circle_from_mask(mask):
    if not mask.any():
        raise ValueError("sphere mask is empty")
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = (labels == biggest).astype(np.uint8)
    contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    pts = max(contours, key=len)[:, 0, :].astype(np.float64)
    if len(pts) < 8:
        raise ValueError("sphere mask is too small to fit a circle")
    # contour pixels are the region's outermost pixel centres: the true edge is half a pixel out
    cx, cy, r = fit_circle(pts)
    return np.array([cx, cy, r + 0.5])


def sphere_normals(shape, circle, *, shrink: float = 1.0):
    """Normals of a sphere's visible half: ``(normals (H, W, 3), inside (H, W) bool)``.

    Pixels inside ``shrink × r`` get ``n = ((x−cx)/r, −(y−cy)/r, √(1−…))`` (x right, y up).
    """
    h, w = shape
    cx, cy, r = _check_circle(circle)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    nx = (cols - cx) / r
    ny = -(rows - cy) / r
    rho2 = nx * nx + ny * ny
    inside = rho2 < shrink * shrink
    nz = np.sqrt(np.clip(1.0 - rho2, 0.0, None))
    n = np.stack([nx, ny, nz], axis=-1)
    n[~inside] = 0.0
    return n, inside


def _grey(images):
    a = np.asarray(images)
    if a.ndim == 4:
        if a.shape[3] != 3:
            raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got {a.shape}")
        return a.astype(np.float32) @ np.array([0.2989, 0.5870, 0.1140], np.float32)
    if a.ndim != 3:
        raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got {a.shape}")
    return a.astype(np.float32)


def highlight_positions(images, circle, *, fraction: float = 0.5) -> np.ndarray:
    """Sub-pixel position ``(x, y)`` of the mirror-sphere highlight in each image.

    The highlight is the connected region of pixels brighter than ``fraction`` of the way from
    the sphere's median to its maximum that contains the maximum; its position is the centroid
    weighted by the intensity above that level (a saturated highlight is a flat disc: its
    centre).

    Raises
    ------
    ValueError
        If an image shows no highlight on the sphere (all pixels equal).
    """
    grey = _grey(images)
    c = _check_circle(circle, grey.shape[1:])
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    _, inside = sphere_normals(grey.shape[1:], c, shrink=0.98)
    pos = np.empty((len(grey), 2))
    for i, im in enumerate(grey):  # one connected-components pass per image
        vals = im[inside]
        top, med = float(vals.max()), float(np.median(vals))
        if top <= med:
            raise ValueError(f"image {i}: no highlight on the mirror sphere (flat intensities)")
        level = med + fraction * (top - med)
        bright = inside & (im >= level)
        _, labels = cv2.connectedComponents(bright.astype(np.uint8), connectivity=8)
        peak = np.unravel_index(np.argmax(np.where(inside, im, -np.inf)), im.shape)
        blob = labels == labels[peak]
        rows, cols = np.nonzero(blob)
        # weights fall to zero at the blob's edge: the centroid moves smoothly, not by whole pixels
        wgt = im[rows, cols] - level + 1e-6 * (top - med)
        pos[i] = (np.sum(cols * wgt) / wgt.sum(), np.sum(rows * wgt) / wgt.sum())
    return pos


def mirror_sphere_directions(images, circle, *, fraction: float = 0.5) -> np.ndarray:
    """Light directions from the highlights on a mirror sphere (thesis §3.2).

    Parameters
    ----------
    images : (N, H, W) or (N, H, W, 3) array
        The flash images (or images of the sphere under the same flashes).
    circle : (cx, cy, r)
        The sphere's outline in pixels (see :func:`find_sphere`).
    fraction : float
        Highlight threshold (see :func:`highlight_positions`).

    Returns
    -------
    (N, 3) array
        Unit light directions (x right, y up, z towards the camera):
        ``l = 2 (n·v) n − v`` with v = (0, 0, 1) and n the sphere normal at the highlight.

    References
    ----------
    Thesis §3.2. The reflection of the view vector about the normal is the mirror law; e.g.
    Hertzmann & Seitz, "Example-based photometric stereo", PAMI 27(8), 2005.
    """
    c = _check_circle(circle)
    pos = highlight_positions(images, c, fraction=fraction)
    nx = (pos[:, 0] - c[0]) / c[2]
    ny = -(pos[:, 1] - c[1]) / c[2]
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, None))
    n = np.column_stack([nx, ny, nz])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    view = np.array([0.0, 0.0, 1.0])
    light = 2.0 * (n @ view)[:, None] * n - view
    return light / np.linalg.norm(light, axis=1, keepdims=True)


def diffuse_sphere_intensities(images, circle, directions, *, valid=None,
                               min_shading: float = 0.2) -> np.ndarray:
    """Relative RGB intensity of each light from a diffuse (Lambertian) sphere (thesis §3.2).

    Parameters
    ----------
    images : (N, H, W, 3) or (N, H, W) float array
        Linear images showing the diffuse sphere.
    circle : (cx, cy, r)
        The sphere's outline in pixels.
    directions : (N, 3) array
        Light directions (from a light file or :func:`mirror_sphere_directions`).
    valid : (N, H, W) bool, optional
        False marks measurements to ignore (saturated).
    min_shading : float
        Only pixels with ``n·l > min_shading`` are fitted (away from the terminator, where
        the Lambertian model and the circle's edge are least reliable).

    Returns
    -------
    (N, 3) array
        Per-light RGB scale ``e_i`` (the least-squares fit of ``I = e_i · n·l`` over the sphere,
        the sphere's albedo folded in), normalised to mean 1 over all lights and channels.
        Divide image *i* by row *i* to equalise the lights.
    """
    imgs = np.asarray(images, dtype=np.float32)
    if imgs.ndim == 3:
        imgs = imgs[..., None].repeat(3, axis=3)
    if imgs.ndim != 4 or imgs.shape[3] != 3:
        raise ValueError(f"images must be (N, H, W) or (N, H, W, 3), got {imgs.shape}")
    n_img, h, w = imgs.shape[:3]
    d = np.asarray(directions, dtype=np.float64)
    if d.shape != (n_img, 3):
        raise ValueError(f"directions must be ({n_img}, 3), got {d.shape}")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    normals, inside = sphere_normals((h, w), circle, shrink=0.95)
    if inside.sum() < 20:
        raise ValueError("the diffuse sphere covers fewer than 20 pixels; check the circle")
    nv = normals[inside]  # (P, 3)
    shade = d @ nv.T  # (N, P)
    use = shade > min_shading
    if valid is not None:
        use &= np.asarray(valid, bool)[:, inside]
    counts = use.sum(1)
    if np.any(counts < 10):
        raise ValueError(f"light {int(np.argmin(counts))} lights fewer than 10 sphere pixels; "
                         f"check its direction and the circle")
    vals = imgs[:, inside]  # (N, P, 3)
    ws = np.where(use, shade, 0.0)
    e = np.einsum("np,npc->nc", ws, vals) / (ws * ws).sum(1)[:, None]
    if not np.all(e > 0):
        raise ValueError("the diffuse sphere is dark under some light: no intensity can be fitted")
    return e / e.mean()
