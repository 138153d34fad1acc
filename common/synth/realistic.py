"""What makes real broken frescoes hard, for the synthetic wall: the ``pompeii`` preset (issue 15).

Measured on the RePAIR fragments from Pompeii (``../shared/data/repair-dev``, see
:mod:`common.synth.stats` and ``docs/synth.md``): pieces of 5-20 cm; material lost along the
cracks, so true neighbours rarely touch (the smallest gap a median of ~1.3 mm, the median gap
along the crack ~3.6 mm); rough, chipped outlines with a soft alpha edge of ~3.4 px; faces that
are mostly plain lime-white or grey plaster (CIELAB chroma ~3) with sparse, faded painted
elements -- bands, lines, borders, small motifs, spotted fields -- that cross the cracks; and
several frescoes painted with one palette.

- :data:`PRESETS` -- the ``generate_wall`` arguments of the ``pompeii`` preset;
- :func:`plaster_palette` -- the colours several walls share (one ``palette_seed``);
- :func:`wall_ground` -- one wall's plaster when the walls of a house share their plaster;
- :func:`paint_plaster` -- a plain plaster wall with sparse painted elements (a
  :class:`~common.synth.painting.Painting`);
- :class:`MaterialLoss` -- how much plaster each crack lost, a function of the crack (the pair
  of pieces) and of the wall position, split unevenly between its two sides;
- :func:`lose_material` -- applies it to one fragment's mask;
- :func:`recovered_region` -- the irregular patch of the wall that is broken and recovered;
- :func:`round_outline` -- roughens and rounds a mask's outline (crumbled, worn edges);
- :func:`fragment_rgba` -- a fragment as an 8-bit RGBA image with a soft alpha edge (RePAIR-like);
- :func:`write_collection` -- a wall written as a RePAIR-layout collection (PNG + ``truth.csv``;
  :func:`write_fragment_png` and :func:`write_truth_csv` to stream it fragment by fragment).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from common.store import atomic_file  # the project's one atomic write (temporary name, then rename)
from common.synth.noise import FractalField
from common.synth.painting import Painting

# generate_wall keyword arguments of the presets (explicit arguments override them)
PRESETS = {
    "pompeii": dict(style="pompeii", median_size_mm=90.0, sigma=0.4, min_size_mm=20.0, max_size_mm=200.0,
                    erosion_mm=0.0, chips_per_cm=0.12, jag_mm=3.0, jag_scale_mm=40.0, round_mm=0.3,
                    edge_noise_mm=0.3, border_weight=0.25, irregular_area=True, surface_wear=False,
                    loss=dict(median_mm=4.2, sigma=0.45, spread=0.6, touch_fraction=0.35), min_shared_mm=10.0,
                    missing_fraction=0.25, spurious_fraction=0.05,
                    fade_fraction=0.1, discolour_fraction=0.1, relief_res_mm=0.5),
}


# ------------------------------------------------------------------------------------ palette
def _lin(srgb):
    x = np.asarray(srgb, np.float64) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


# sRGB colours of plaster grounds and of faded pigments on Pompeian fragments (as scanned)
_GROUNDS = {"lime white": (172, 168, 164), "grey": (160, 158, 157), "warm grey": (170, 163, 160),
            "pinkish grey": (171, 162, 163)}
_PAINTS = {"red ochre": (166, 118, 112), "purple": (146, 116, 130), "pink": (182, 146, 146),
           "yellow ochre": (186, 164, 120), "green earth": (136, 150, 136), "grey-green": (148, 158, 150),
           "black": (96, 94, 96), "white": (200, 198, 194), "blue-grey": (134, 144, 160)}


def plaster_palette(palette_seed: int) -> dict:
    """The colours a group of walls shares: plaster grounds and a few faded pigments.

    Parameters
    ----------
    palette_seed : int
        Walls made with the same palette seed (and any wall seed) are painted with the same
        colours, as the frescoes of one house are.

    Returns
    -------
    dict
        ``grounds`` (list of linear RGB), ``paints`` (dict name -> linear RGB, 4-6 of them).
    """
    rng = np.random.default_rng([int(palette_seed), 7411])

    def jitter(c, s):  # brightness and (less) hue
        return np.clip(_lin(np.asarray(c) + rng.normal(0, s) + rng.normal(0, s / 4, 3)), 0, 1).astype(np.float32)

    grounds = [jitter(c, 3.0) for c in _GROUNDS.values()]
    names = sorted(_PAINTS)
    chosen = ["red ochre"] + list(rng.choice([n for n in names if n != "red ochre"], int(rng.integers(3, 6)),
                                            replace=False))
    paints = {n: jitter(_PAINTS[n], 6.0) for n in chosen}
    # drawn last, so the grounds and paints above do not depend on it
    house = int(rng.integers(len(grounds)))
    return dict(grounds=grounds, paints=paints, house_ground=grounds[house])


def wall_ground(palette: dict, wall_seed: int, *, jitter_srgb: float = 3.0) -> np.ndarray:
    """The plaster ground of one wall of a house whose walls share their plaster.

    The frescoes of one house were laid on one lime mix (``palette["house_ground"]``); each wall's
    batch and ageing shift its tone a little: a brightness offset ``N(0, jitter_srgb)`` and a tint
    ``N(0, jitter_srgb / 4)`` per channel (8-bit sRGB levels), as :func:`plaster_palette` jitters its
    colours. Used by ``generate_wall(..., house_plaster=True)``; measured against RePAIR's frescoes in
    docs/matching.md ("Which fresco a piece comes from").

    Parameters
    ----------
    palette : dict
        From :func:`plaster_palette`.
    wall_seed : int
        The wall's seed.
    jitter_srgb : float
        Wall-to-wall brightness spread, 8-bit sRGB levels.

    Returns
    -------
    (3,) float32
        Linear RGB.
    """
    if "house_ground" not in palette:
        raise ValueError("palette has no 'house_ground' (make it with plaster_palette)")
    rng = np.random.default_rng([int(wall_seed), 4243])
    srgb = np.where(palette["house_ground"] <= 0.0031308, 12.92 * palette["house_ground"],
                    1.055 * np.power(palette["house_ground"], 1 / 2.4) - 0.055) * 255.0
    return np.clip(_lin(srgb + rng.normal(0, jitter_srgb) + rng.normal(0, jitter_srgb / 4, 3)), 0, 1).astype(np.float32)


# ----------------------------------------------------------------------------------- painting
def paint_plaster(width_mm: float, height_mm: float, rng: np.random.Generator, *, palette: dict | None = None,
                  res_mm: float = 0.4, ground: np.ndarray | None = None) -> Painting:
    """A mostly plain plaster wall with sparse, faded painted elements.

    Plain lime-white or grey plaster (mottled at centimetre scale, speckled by the aggregate)
    carries a few horizontal bands and borders of thin lines, some framing lines, small motifs
    (leaves, dots, rosettes) and sometimes a stippled field (spots on a coloured ground, as on
    RePAIR's g13). Paint is applied with an uneven opacity, so it looks faded and patchy.

    Parameters
    ----------
    width_mm, height_mm : float
        Wall size.
    rng : numpy.random.Generator
    palette : dict, optional
        From :func:`plaster_palette` (default: palette seed 0).
    res_mm : float
        Raster pixel size (0.4 mm: the painted elements are broad and faded; sampling a
        fragment interpolates it bilinearly).
    ground : (3,) array, optional
        The plaster's linear RGB (:func:`wall_ground`); default one of the palette's grounds, drawn
        from ``rng``.

    Returns
    -------
    Painting
        With the band edges as layout strings (snapped lines) and no incisions.

    Examples
    --------
    >>> p = paint_plaster(200, 150, np.random.default_rng(0), res_mm=1.0)
    >>> p.albedo.shape
    (150, 200, 3)
    """
    if not (width_mm > 0 and height_mm > 0):
        raise ValueError(f"width_mm and height_mm must be positive, got {width_mm}, {height_mm}")
    if res_mm <= 0:
        raise ValueError(f"res_mm must be positive, got {res_mm}")
    palette = plaster_palette(0) if palette is None else palette
    W, H = int(np.ceil(width_mm / res_mm)), int(np.ceil(height_mm / res_mm))
    k = 1.0 / res_mm
    G = np.array([[res_mm, 0.0, 0.0], [0.0, res_mm, 0.0]])
    drawn = palette["grounds"][int(rng.integers(len(palette["grounds"])))]   # drawn either way: same stream
    ground = drawn if ground is None else np.asarray(ground, np.float32)
    img = np.empty((H, W, 3), np.float32)
    img[:] = ground
    # centimetre-scale mottling (lime wash, dirt) and a second, greyer blotching
    lum = FractalField(rng, 30.0, octaves=4, persistence=0.6, amplitude=0.05).grid(G, (H, W))
    img *= (1.0 + lum)[..., None]
    warm = FractalField(rng, 25.0, octaves=4, persistence=0.7, amplitude=0.012).grid(G, (H, W))
    img[..., 0] *= 1.0 + warm
    img[..., 2] *= 1.0 - warm
    paints = palette["paints"]
    names = list(paints)
    strings: list = []
    # coverage per pigment, composited at the end
    cover = {n: np.zeros((H, W), np.float32) for n in names}
    spots = {}  # the spots of a stippled field, composited over everything else

    def pick():
        return names[int(rng.integers(len(names)))]

    def line(name, pts_mm, width_mm_, closed=False):
        pts = np.round(np.asarray(pts_mm) * k * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.polylines(cover[name], [pts], closed, 1.0, max(1, int(round(width_mm_ * k))), cv2.LINE_AA, shift=4)

    def fill(name, pts_mm):
        pts = np.round(np.asarray(pts_mm) * k * 16).astype(np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(cover[name], [pts], 1.0, cv2.LINE_AA, shift=4)

    area = width_mm * height_mm
    tilt = np.deg2rad(rng.normal(0, 1.5))
    # horizontal bands and borders (a band with thin lines beside it)
    n_bands = int(rng.poisson(area / 150_000.0)) + int(rng.random() < 0.7)
    for _ in range(n_bands):
        y = rng.uniform(0.05, 0.95) * height_mm
        h = float(np.exp(rng.uniform(np.log(5.0), np.log(45.0))))
        name = pick()
        xs = np.array([-10.0, width_mm + 10.0])
        ys = y + np.tan(tilt) * xs
        fill(name, np.array([[xs[0], ys[0]], [xs[1], ys[1]], [xs[1], ys[1] + h], [xs[0], ys[0] + h]]))
        strings += [((xs[0], ys[0]), (xs[1], ys[1])), ((xs[0], ys[0] + h), (xs[1], ys[1] + h))]
        if rng.random() < 0.6:  # border lines beside the band
            other = pick()
            for side in (-1, 1) if rng.random() < 0.5 else (int(rng.choice([-1, 1])),):
                off = rng.uniform(3.0, 9.0)
                yy = (ys - off) if side < 0 else (ys + h + off)
                line(other, np.column_stack([xs, yy]), rng.uniform(0.8, 2.5))
    # framing lines (horizontal / vertical, sometimes a rectangle)
    for _ in range(int(rng.poisson(area / 100_000.0)) + 1):
        name, w = pick(), rng.uniform(0.8, 3.0)
        if rng.random() < 0.4:
            x0, y0 = rng.uniform(0, width_mm), rng.uniform(0, height_mm)
            x1, y1 = x0 + rng.uniform(80, 400), y0 + rng.uniform(80, 400)
            line(name, [[x0, y0], [x1, y0], [x1, y1], [x0, y1]], w, closed=True)
        elif rng.random() < 0.5:
            y = rng.uniform(0, height_mm)
            line(name, [[-10, y], [width_mm + 10, y + np.tan(tilt) * width_mm]], w)
        else:
            x = rng.uniform(0, width_mm)
            line(name, [[x, -10], [x - np.tan(tilt) * height_mm, height_mm + 10]], w)
    # a stippled field: spots on a coloured ground
    if rng.random() < 0.35:
        x0, y0 = rng.uniform(-0.2, 0.6) * width_mm, rng.uniform(-0.2, 0.6) * height_mm
        fw, fh = rng.uniform(0.3, 0.8) * width_mm, rng.uniform(0.3, 0.8) * height_mm
        g_name = pick()
        fill(g_name, [[x0, y0], [x0 + fw, y0], [x0 + fw, y0 + fh], [x0, y0 + fh]])
        s_name = names[(names.index(g_name) + 1 + int(rng.integers(len(names) - 1))) % len(names)]
        sp = rng.uniform(7.0, 14.0)
        r = rng.uniform(0.15, 0.3) * sp
        for yy in np.arange(y0, y0 + fh, sp):
            shift = sp / 2 if int((yy - y0) / sp) % 2 else 0.0
            for xx in np.arange(x0 + shift, x0 + fw, sp):
                c = (xx + rng.normal(0, 0.08 * sp), yy + rng.normal(0, 0.08 * sp))
                ax = (max(1, int(r * k * rng.uniform(0.8, 1.3))), max(1, int(r * k * rng.uniform(0.5, 1.0))))
                layer = spots.setdefault(s_name, np.zeros((H, W), np.float32))
                cv2.ellipse(layer, (int(c[0] * k), int(c[1] * k)), ax, float(rng.uniform(0, 180)), 0, 360,
                            1.0, -1, cv2.LINE_AA)
    # small motifs: leaves, dots, rosettes
    for _ in range(int(rng.poisson(area / 25_000.0))):
        cx, cy = rng.uniform(0, width_mm), rng.uniform(0, height_mm)
        name = pick()
        kind = rng.random()
        if kind < 0.4:  # a leaf: two arcs
            L, wd, a = rng.uniform(8, 30), rng.uniform(3, 10), rng.uniform(0, np.pi)
            t = np.linspace(0, 1, 24)
            u = (t - 0.5) * L
            v = wd / 2 * np.sin(np.pi * t)
            pts = np.vstack([np.column_stack([u, v]), np.column_stack([u[::-1], -v[::-1]])])
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            fill(name, pts @ R.T + (cx, cy))
        elif kind < 0.7:  # a rosette of dots
            rr, dot = rng.uniform(3, 10), rng.uniform(0.8, 2.0)
            for a in np.linspace(0, 2 * np.pi, int(rng.integers(5, 9)), endpoint=False):
                cv2.circle(cover[name], (int((cx + rr * np.cos(a)) * k), int((cy + rr * np.sin(a)) * k)),
                           max(1, int(dot * k)), 1.0, -1, cv2.LINE_AA)
        else:  # a curved stroke (tendril)
            t = np.linspace(0, 1, 30)[:, None]
            p0 = np.array([cx, cy])
            p1, p2 = p0 + rng.normal(0, 15, 2), p0 + rng.normal(0, 25, 2)
            line(name, (1 - t) ** 2 * p0 + 2 * t * (1 - t) * p1 + t ** 2 * p2, rng.uniform(0.8, 2.5))
    # faint washes and stains: large soft patches of a pigment at low opacity
    wash = {}
    for _ in range(int(rng.poisson(area / 100_000.0))):
        name = pick()
        layer = wash.setdefault(name, np.zeros((H, W), np.float32))
        r = rng.uniform(15, 80)
        cv2.circle(layer, (int(rng.uniform(0, width_mm) * k), int(rng.uniform(0, height_mm) * k)), int(r * k),
                   float(rng.uniform(0.05, 0.15)), -1, cv2.LINE_AA)
    for n, a in wash.items():
        # soft edges: blurred on a 4x coarser raster, then interpolated back
        small = cv2.resize(a, (max(1, W // 4), max(1, H // 4)), interpolation=cv2.INTER_AREA)
        a = cv2.resize(cv2.GaussianBlur(small, (0, 0), 2.0 * k), (W, H), interpolation=cv2.INTER_LINEAR)
        img += a[..., None] * (np.asarray(paints[n], np.float32) - img)
    # composite with patchy opacity (faded, worn paint)
    patch = FractalField(rng, 6.0, octaves=3, persistence=0.6, amplitude=0.25).grid(G, (H, W))
    opacity = np.clip(rng.uniform(0.35, 0.65) + patch, 0.05, 1.0)
    for n, a in list(cover.items()) + list(spots.items()):
        if not a.any():
            continue
        a *= opacity
        img += a[..., None] * (np.asarray(paints[n], np.float32) * (1.0 + lum)[..., None] - img)
    # plaster aggregate: small light and dark grains
    n_grain = int(area * 0.05)
    spk = np.zeros((H, W), np.float32)
    idx = rng.integers(0, H * W, n_grain)
    spk.ravel()[idx] = rng.normal(0, 1.0, n_grain).astype(np.float32)
    spk = cv2.GaussianBlur(spk, (0, 0), max(0.3 * k, 0.5)) * (0.3 * k)
    img *= (1.0 + np.clip(spk, -0.12, 0.12))[..., None]
    img *= 1.0 + FractalField(rng, 1.0, octaves=2, amplitude=0.015).grid(G, (H, W))[..., None]
    np.clip(img, 0.0, 1.0, out=img)
    return Painting(img, float(res_mm), strings, [])


# ------------------------------------------------------------------------- recovered area
REGION_FRACTION = 0.64  # the share of the wall rectangle the walls are sized for (recovered_region keeps 0.45-0.85, mean 0.58 over 200 seeds)
#: Bounds of that share for any one wall: at the fixed threshold alone a fractal field that happens to be
#: low over the middle kept under 20 % of the rectangle for one seed in ten, nothing for some (the wall,
#: sized for REGION_FRACTION, then broke into crumbs far below the preset's sizes, or into no piece).
REGION_SHARE_BOUNDS = (0.45, 0.85)


def recovered_region(width_mm: float, height_mm: float, rng: np.random.Generator, *, roughness: float = 0.5):
    """An irregular recovered patch of a wall, instead of the whole rectangle.

    Real collapsed frescoes are recovered as irregular groups of pieces; a piece on the
    rectangle's edge would show a long straight side no real fragment has. The wall is kept where
    ``1 - r^2 + F > t`` (``r`` the elliptical radius from the centre, ``F`` a fractal field of
    std ``roughness`` at a third of the wall's size, ``t`` = 0.3); about :data:`REGION_FRACTION` of the
    rectangle. Where that would keep a share outside :data:`REGION_SHARE_BOUNDS` (a field low or high
    over most of the wall), ``t`` is moved to keep the nearer bound, so every wall is sized for the
    pieces its preset asks for. The fracture evaluates it at its warped coordinates (``keep`` argument of
    :func:`~common.synth.breakage.fracture_recursive`), so the patch's edge is as jagged as the
    cracks and the pieces are counted inside it.

    Parameters
    ----------
    width_mm, height_mm : float
        The wall rectangle.
    rng : numpy.random.Generator
    roughness : float
        Irregularity of the patch outline.

    Returns
    -------
    callable(x_mm, y_mm) -> bool array
    """
    if roughness < 0:
        raise ValueError(f"roughness must be >= 0, got {roughness}")
    W, H = float(width_mm), float(height_mm)
    field = FractalField(rng, max(W, H) / 3.0, octaves=3, persistence=0.5, amplitude=roughness)

    def level(x, y):
        shape = np.shape(x)
        x, y = np.ravel(x).astype(np.float32), np.ravel(y).astype(np.float32)
        n = x.size
        pad = (-n) % 1024  # the field is sampled with cv2.remap: rows of at most 1024 points
        xr, yr = np.pad(x, (0, pad)).reshape(-1, 1024), np.pad(y, (0, pad)).reshape(-1, 1024)
        f = field(xr, yr).ravel()[:n]
        r2 = ((x - W / 2) / (W / 2)) ** 2 + ((y - H / 2) / (H / 2)) ** 2
        return (1.0 - r2 + f).reshape(shape)

    # the share kept, on a 128 x 128 grid of the rectangle
    gy, gx = np.meshgrid(np.linspace(0.0, H, 128), np.linspace(0.0, W, 128), indexing="ij")
    sample = level(gx, gy).ravel()
    threshold = 0.3
    share = float(np.mean(sample > threshold))
    low, high = REGION_SHARE_BOUNDS
    if share < low or share > high:
        threshold = float(np.quantile(sample, 1.0 - (low if share < low else high)))

    def keep(x, y):
        return level(x, y) > threshold

    return keep


# ---------------------------------------------------------------------------- material loss
@dataclass
class MaterialLoss:
    """Plaster lost along the cracks: the gap it leaves between two pieces that once joined.

    At a wall point ``p`` on the crack between pieces ``a < b`` the gap is
    ``g(p) = max(0, s_ab * exp(k_ab * F(p)) - d_ab)``: ``s_ab`` a log-normal scale per crack
    (median ``median_mm``, log-sd ``sigma``), ``F`` a unit fractal field along the wall (so the
    gap varies along the crack) with a per-crack spread ``k_ab`` (``spread`` x 0.5-1.5),
    ``d_ab`` an offset that lets a share ``touch_fraction`` of cracks close up somewhere. Piece ``a`` loses ``w(p) g(p)`` and ``b`` loses ``(1 - w(p)) g(p)``, with
    ``w`` a smooth field in (0.1, 0.9): uneven, both sides.

    Parameters
    ----------
    seed : int
    median_mm, sigma : float
        Log-normal scale of a crack's gap.
    spread : float
        Log-sd of the variation along a crack.
    scale_mm : float
        Correlation length of that variation.
    touch_fraction : float
        Share of cracks whose gap closes to zero somewhere.
    """

    seed: int
    median_mm: float = 3.0
    sigma: float = 0.45
    spread: float = 0.55
    scale_mm: float = 15.0
    touch_fraction: float = 0.3

    def __post_init__(self):
        if self.median_mm < 0 or self.sigma < 0 or self.spread < 0 or self.scale_mm <= 0:
            raise ValueError("MaterialLoss: median_mm, sigma and spread must be >= 0 and scale_mm positive")
        if not 0 <= self.touch_fraction <= 1:
            raise ValueError(f"touch_fraction must be in [0, 1], got {self.touch_fraction}")
        rng = np.random.default_rng([int(self.seed), 5133])
        self._vary = FractalField(rng, self.scale_mm, octaves=3, persistence=0.5, amplitude=1.0)
        self._split = FractalField(rng, 2.0 * self.scale_mm, octaves=2, persistence=0.5, amplitude=1.0)
        self._norm = 1.0 / np.sqrt(1 + 0.25 + 0.0625)  # unit variance of the three octaves

    def crack(self, a: int, b: int) -> tuple[float, float, float]:
        """(scale s, offset d, spread) of the crack between pieces ``a`` and ``b`` (-1 = outside);
        the spread along a crack is ``spread`` times a factor in [0.5, 1.5]."""
        lo, hi = sorted((int(a), int(b)))
        rng = np.random.default_rng([int(self.seed), lo + 2, hi + 2])
        s = self.median_mm * float(np.exp(self.sigma * rng.standard_normal()))
        d = s * float(rng.uniform(0.35, 0.9)) if rng.random() < self.touch_fraction else 0.0
        return s, d, self.spread * float(rng.uniform(0.5, 1.5))

    def depth_grid(self, G: np.ndarray, shape, label: int, other: np.ndarray) -> np.ndarray:
        """Depth (mm) piece ``label`` loses at each pixel of an affine grid, given the piece
        ``other`` (int array, -1 = outside the wall) across the nearest crack."""
        vary = self._norm * self._vary.grid(G, shape)
        w = 0.1 + 0.8 / (1.0 + np.exp(-1.5 * self._split.grid(G, shape)))
        out = np.zeros(shape, np.float32)
        for m in np.unique(other):
            sel = other == m
            s, d, spread = self.crack(label, m)
            g = np.maximum(0.0, s * np.exp(spread * vary[sel]) - d)
            share = w[sel] if label < m else 1.0 - w[sel]
            out[sel] = g * share
        return out


def lose_material(mask: np.ndarray, labels: np.ndarray, label: int, G: np.ndarray, loss: MaterialLoss) -> np.ndarray:
    """Remove the plaster ``loss`` takes from one fragment's freshly broken mask.

    Parameters
    ----------
    mask : (H, W) bool
        The fragment before loss.
    labels : (H, W) int
        Piece labels on the same grid (-1 = outside the wall); the pieces across the cracks.
    label : int
        This fragment's piece label.
    G : (2, 3) array
        Pixel grid -> wall mm (``wall = G @ (col, row, 1)``).
    loss : MaterialLoss

    Returns
    -------
    (H, W) bool
        Mask of what is left (pixels deeper inside than the loss at their crack).
    """
    if mask.shape != labels.shape:
        raise ValueError(f"mask {mask.shape} and labels {labels.shape} must have one shape")
    pm = float(np.hypot(G[0, 0], G[1, 0]))
    src = np.pad(mask.astype(np.uint8), 1)
    lab_p = np.pad(labels, 1, constant_values=-1)
    dist, idx = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    # label of each outside pixel (the zero pixels are numbered in raster order)
    zr, zc = np.nonzero(src == 0)
    zero_lab = np.full(idx.max() + 1, -1, np.int32)
    zero_lab[idx[zr, zc]] = lab_p[zr, zc]
    other = zero_lab[idx][1:-1, 1:-1]
    dist = dist[1:-1, 1:-1] * pm
    depth = loss.depth_grid(G, mask.shape, label, np.where(mask, other, -1))
    return mask & (dist > depth)


def round_outline(mask: np.ndarray, radius_px: float, *, noise_px: np.ndarray | None = None) -> np.ndarray:
    """Round a mask's outline, optionally roughening it first.

    Parameters
    ----------
    mask : (H, W) bool
    radius_px : float
        Gaussian blur radius; the blurred mask is re-thresholded at 0.5, so convex tips and
        narrow notches soften, as on worn fragments.
    noise_px : (H, W) float array, optional
        Outward displacement of the outline (px) before rounding: fine jaggedness (crumbled edge).

    Returns
    -------
    (H, W) bool
        Never larger than ``mask``.
    """
    out = mask
    if noise_px is not None:
        m8 = np.pad(mask.astype(np.uint8), 1)
        sd = (cv2.distanceTransform(m8, cv2.DIST_L2, 5) - cv2.distanceTransform(1 - m8, cv2.DIST_L2, 5))[1:-1, 1:-1]
        out = (sd + noise_px - 0.5 > 0) & mask
    if radius_px > 0:
        out = (cv2.GaussianBlur(out.astype(np.float32), (0, 0), float(radius_px)) > 0.5) & out
    return out


# ------------------------------------------------------------------------------------ output
def fragment_rgba(rgbn, *, edge_px: float | None = None) -> np.ndarray:
    """A fragment as an 8-bit sRGB RGBA image with a soft alpha edge, as RePAIR's images are.

    Parameters
    ----------
    rgbn : RGBNImage
        The fragment (colour and mask).
    edge_px : float, optional
        Width of the band of partial alpha across the outline (px; default 0.46 mm at the
        image's dpi, at least 1.5 px: 3.4 px at 187 dpi, RePAIR's measured 3.4 partial pixels
        per pixel of outline). The ramp is the mask blurred by a Gaussian of edge_px / 5.3.

    Returns
    -------
    (H + 2p, W + 2p, 4) uint8
        Padded by ``p = ceil(edge_px)`` pixels; colour 0 where alpha is 0.
    """
    from common.synth.figures import to_srgb8

    if edge_px is None:
        edge_px = max(1.5, 0.46 / rgbn.pixel_mm)
    if edge_px < 0:
        raise ValueError(f"edge_px must be >= 0, got {edge_px}")
    p = int(np.ceil(edge_px)) + 1
    mask = np.pad(rgbn.mask, p)
    albedo = np.pad(rgbn.albedo, ((p, p), (p, p), (0, 0)))
    # a blurred mask: a sub-pixel ramp with soft tails, partial (0 < alpha < 255) over ~edge_px
    # (a Gaussian step is between 0.5/255 and 254.5/255 over 5.3 sigma)
    alpha = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), edge_px / 5.3) if edge_px > 0 \
        else mask.astype(np.float32)
    # colour just outside: the nearest inside colour (dilated)
    rgb = to_srgb8(albedo)
    ring = (alpha > 0) & ~mask
    if ring.any():
        grown = rgb.copy()
        filled = mask.copy()
        kernel = np.ones((3, 3), np.uint8)
        for _ in range(p):
            dil = cv2.dilate(grown * filled[..., None], kernel)
            cnt = cv2.dilate(filled.astype(np.uint8), kernel).astype(bool)
            new = cnt & ~filled
            grown[new] = dil[new]
            filled |= new
        rgb[ring] = grown[ring]
    a8 = np.round(alpha * 255).astype(np.uint8)
    rgb[a8 == 0] = 0
    return np.dstack([rgb, a8])


def write_collection(wall, directory: str | os.PathLike, fragments=None, *, edge_px: float | None = None) -> Path:
    """Write a wall as a RePAIR-layout collection: ``<dir>/<wall id>/<fragment id>.png`` (RGBA,
    square canvas, piece centred) and ``truth.csv`` (``rpf,x,y,rot``: rotate the image
    counter-clockwise by ``rot`` about its centre, canvas kept, put its top-left corner at (x, y)
    on the wall canvas at the wall's dpi). Spurious fragments go to ``<dir>/<wall id>-spurious/``
    without a ``truth.csv`` (distractors).

    Parameters
    ----------
    wall : Wall
    directory : path
    fragments : list of Fragment, optional
        Fragments with images (default ``wall.fragments``).
    edge_px : float, optional
        Soft alpha edge (see :func:`fragment_rgba`).

    Returns
    -------
    Path
        The wall's folder.
    """
    rows = [write_fragment_png(f, directory, wall.id, edge_px=edge_px)
            for f in (wall.fragments if fragments is None else fragments)]
    return write_truth_csv(directory, wall.id, [r for r in rows if r is not None])


def write_fragment_png(fragment, directory: str | os.PathLike, wall_id: str, *,
                       edge_px: float | None = None) -> tuple | None:
    """Write one fragment of :func:`write_collection` (atomically); return its ``truth.csv`` row
    ``(file, x, y, rot)``, or None for a spurious fragment."""
    f = fragment
    if f.rgbn is None:
        raise ValueError(f"fragment {f.id} has no image (generate with keep_images=True)")
    if edge_px is None:
        edge_px = max(1.5, 0.46 / f.rgbn.pixel_mm)
    rgba = fragment_rgba(f.rgbn, edge_px=edge_px)
    p = int(np.ceil(edge_px)) + 1  # fragment_rgba's padding
    h, w = rgba.shape[:2]
    side = int(np.ceil(np.hypot(h, w))) + 2
    side += side % 2
    r0, c0 = (side - h) // 2, (side - w) // 2
    canvas = np.zeros((side, side, 4), np.uint8)
    canvas[r0:r0 + h, c0:c0 + w] = rgba
    folder = Path(directory) / (wall_id if f.pose is not None else f"{wall_id}-spurious")
    folder.mkdir(parents=True, exist_ok=True)
    ok, png = cv2.imencode(".png", np.ascontiguousarray(canvas[..., [2, 1, 0, 3]]), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise ValueError(f"fragment {f.id}: PNG encoding failed")
    with atomic_file(folder / f"{f.id}.png") as tmp:
        Path(tmp).write_bytes(png.tobytes())
    if f.pose is None:
        return None
    # canvas pixel u = fragment pixel + (c0 + p, r0 + p); wall px = R (col, row) + t / pm
    pm = f.rgbn.pixel_mm
    a = np.deg2rad(f.pose[0])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = np.asarray(f.pose[1:]) / pm - R @ (c0 + p, r0 + p)  # canvas px -> wall px: R u + t
    c = np.array([side / 2.0, side / 2.0])
    xy = t - c + R @ c  # getRotationMatrix2D(c, rot) = [R | c - R c], then + (x, y)
    return (f"{f.id}.png", float(xy[0]), float(xy[1]), float(-f.pose[0]))


def write_truth_csv(directory: str | os.PathLike, wall_id: str, rows: list) -> Path:
    """Write ``<dir>/<wall id>/truth.csv`` from :func:`write_fragment_png` rows (atomically)."""
    out = Path(directory) / wall_id
    out.mkdir(parents=True, exist_ok=True)
    lines = ["rpf,x,y,rot"] + [f"{n},{x:.3f},{y:.3f},{r:.6f}" for n, x, y, r in rows]
    with atomic_file(out / "truth.csv") as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return out
