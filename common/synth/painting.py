"""The painted layer of a synthetic wall painting.

A composition in the manner of Aegean (Theran) and Roman wall paintings: a dado, registers of
coloured bands laid out with snapped strings, a frieze of running spirals, large white or solid
fields (Roman panels with framing lines) and figurative shapes (plant- and bird-like blobs with
dark outlines). The result is a raster in wall millimetres that any point of the wall can be
sampled from; the layout lines (string impressions) and incised outlines are returned too, so the
relief can press them into the plaster along the colour boundaries.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from common.synth.noise import FractalField, sample_raster_grid

# linear-RGB pigments of Aegean and Roman palettes (approximate reflectances)
PIGMENTS = {
    "lime white": (0.80, 0.77, 0.70),
    "red ochre": (0.42, 0.12, 0.07),
    "yellow ochre": (0.66, 0.47, 0.17),
    "egyptian blue": (0.12, 0.25, 0.50),
    "green earth": (0.24, 0.33, 0.22),
    "carbon black": (0.05, 0.05, 0.05),
    "pink": (0.72, 0.42, 0.36),
    "cinnabar": (0.55, 0.08, 0.05),
    "grey": (0.35, 0.35, 0.35),
}
_FIELD = ["lime white", "lime white", "lime white", "red ochre", "yellow ochre", "cinnabar", "carbon black"]


@dataclass
class Painting:
    """A painted wall raster.

    Attributes
    ----------
    albedo : (H, W, 3) float32
        Linear RGB reflectance, pixel (r, c) centred at wall point (c * res_mm, r * res_mm).
    res_mm : float
        Raster pixel size in mm.
    string_lines : list of ((x0, y0), (x1, y1))
        Straight layout strings snapped into the wet plaster, wall mm.
    incisions : list of (K, 2) arrays
        Incised polylines (wall mm).
    """

    albedo: np.ndarray
    res_mm: float
    string_lines: list = field(default_factory=list)
    incisions: list = field(default_factory=list)

    @property
    def size_mm(self) -> tuple[float, float]:
        """(width, height) of the wall in mm."""
        return self.albedo.shape[1] * self.res_mm, self.albedo.shape[0] * self.res_mm

    def sample(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Albedo at wall points (mm), bilinear; points outside the wall get the border colour."""
        shape = np.shape(x_mm)
        u = np.atleast_2d(np.asarray(x_mm, np.float32) / np.float32(self.res_mm))
        v = np.atleast_2d(np.asarray(y_mm, np.float32) / np.float32(self.res_mm))
        return cv2.remap(self.albedo, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(shape + (3,))

    def sample_grid(self, G: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Albedo on an affine pixel grid ``wall = G @ (col, row, 1)``, (H, W, 3)."""
        return sample_raster_grid(self.albedo, self.res_mm, G, shape)


def _poly(img, pts_px, colour, *, closed=True, thickness=None, aa=True):
    pts = np.round(np.asarray(pts_px) * 16).astype(np.int32).reshape(-1, 1, 2)
    lt = cv2.LINE_AA if aa else cv2.LINE_8
    if thickness is None:
        cv2.fillPoly(img, [pts], colour, lineType=lt, shift=4)
    else:
        cv2.polylines(img, [pts], closed, colour, thickness=max(int(round(thickness)), 1), lineType=lt, shift=4)


def _spiral(cx, cy, r_out, turns, phase, handed, n=200):
    """Archimedean spiral from the centre outwards, wall mm."""
    t = np.linspace(0.0, 1.0, n)
    ang = phase + handed * 2 * np.pi * turns * t
    r = r_out * (0.08 + 0.92 * t)
    return np.column_stack([cx + r * np.cos(ang), cy + r * np.sin(ang)])


def _blob(rng, cx, cy, r0, n=120):
    """A smooth star-shaped blob (figurative shape), wall mm."""
    th = np.linspace(0, 2 * np.pi, n, endpoint=False)
    r = np.ones(n)
    for k in range(2, 6):
        r += rng.uniform(0, 0.35 / k * 2.5) * np.cos(k * th + rng.uniform(0, 2 * np.pi))
    r *= r0 / r.max()
    sx, sy = rng.uniform(0.6, 1.4), rng.uniform(0.6, 1.4)
    ang = rng.uniform(0, np.pi)
    x, y = r * np.cos(th) * sx, r * np.sin(th) * sy
    c, s = np.cos(ang), np.sin(ang)
    return np.column_stack([cx + c * x - s * y, cy + s * x + c * y])


def paint_wall(width_mm: float, height_mm: float, rng: np.random.Generator, *, res_mm: float = 0.25,
               style: str = "aegean") -> Painting:
    """Paint a wall in the manner of Aegean or Roman wall paintings.

    Parameters
    ----------
    width_mm, height_mm : float
        Wall size in millimetres.
    rng : numpy.random.Generator
        Source of all randomness (same state -> same painting).
    res_mm : float
        Raster pixel size (mm); 0.25 mm keeps colour edges sharp at scan resolution.
    style : {'aegean', 'roman'}
        'aegean': registers of bands, running spirals, plant and bird shapes on white or solid
        grounds; 'roman': large red/black/yellow panels with framing bands and thin lines.

    Returns
    -------
    Painting

    References
    ----------
    Thesis §5.3.3 (the painted and broken test fresco); Shin et al. 2012 on Theran wall paintings.

    Examples
    --------
    >>> p = paint_wall(100, 80, np.random.default_rng(0), res_mm=1.0)
    >>> p.albedo.shape
    (80, 100, 3)
    """
    if not (width_mm > 0 and height_mm > 0):
        raise ValueError(f"width_mm and height_mm must be positive, got {width_mm}, {height_mm}")
    if res_mm <= 0:
        raise ValueError(f"res_mm must be positive, got {res_mm}")
    if style not in ("aegean", "roman"):
        raise ValueError(f"style must be 'aegean' or 'roman', got {style!r}")
    W, H = int(np.ceil(width_mm / res_mm)), int(np.ceil(height_mm / res_mm))
    k = 1.0 / res_mm  # px per mm
    img = np.zeros((H, W, 3), np.float32)
    strings: list = []
    incisions: list = []

    def col(name):
        return tuple(float(c) for c in PIGMENTS[name])

    def hband(y0, y1, name):
        img[int(round(y0 * k)):int(round(y1 * k))] = col(name)
        for y in (y0, y1):
            if 0 < y < height_mm:
                strings.append(((0.0, float(y)), (float(width_mm), float(y))))

    # ground
    ground = rng.choice(_FIELD)
    img[:] = col(ground)
    # registers from the bottom: dado, band stack, main field, frieze, top bands
    y = height_mm
    dado_h = rng.uniform(0.12, 0.25) * height_mm
    hband(y - dado_h, y, rng.choice(["red ochre", "carbon black", "yellow ochre", "cinnabar"]))
    y -= dado_h
    top = rng.uniform(0.0, 0.08) * height_mm
    # stacks of bands between registers
    def band_stack(y_bottom):
        yy = y_bottom
        for _ in range(rng.integers(2, 5)):
            h = rng.uniform(4, 25)
            name = rng.choice(list(PIGMENTS))
            hband(yy - h, yy, name)
            if h > 10 and rng.random() < 0.4:  # a wavy line running along the band
                xs = np.linspace(0, width_mm, max(2, int(width_mm)))
                period, amp = rng.uniform(15, 50), 0.3 * h
                wave = np.column_stack([xs, yy - h / 2 + amp * np.sin(2 * np.pi * xs / period + rng.uniform(0, 6.3))])
                other = rng.choice([c for c in PIGMENTS if c != name])
                _poly(img, wave * k, col(other), closed=False, thickness=rng.uniform(1.0, 3.0) * k)
            yy -= h
        return yy
    y = band_stack(y)
    frieze_h = rng.uniform(30, 70) if height_mm > 150 else 0.0
    field_bottom = y
    field_top = top + frieze_h + (rng.uniform(10, 40) if frieze_h else 0.0)
    if style == "roman":
        # panels with framing bands and thin lines
        n_pan = max(1, int(width_mm // rng.uniform(150, 300)))
        edges = np.linspace(0, width_mm, n_pan + 1)
        for a, b in zip(edges[:-1], edges[1:]):
            name = rng.choice(["red ochre", "carbon black", "yellow ochre", "cinnabar", "lime white"])
            m = rng.uniform(8, 20)
            x0, x1, y0, y1 = a + m, b - m, field_top + m, field_bottom - m
            if x1 - x0 < 20 or y1 - y0 < 20:
                continue
            img[int(y0 * k):int(y1 * k), int(x0 * k):int(x1 * k)] = col(name)
            strings += [((x0, y0), (x1, y0)), ((x0, y1), (x1, y1)), ((x0, y0), (x0, y1)), ((x1, y0), (x1, y1))]
            inset = rng.uniform(4, 10)
            line = np.array([[x0 + inset, y0 + inset], [x1 - inset, y0 + inset],
                             [x1 - inset, y1 - inset], [x0 + inset, y1 - inset]]) * k
            _poly(img, line, col(rng.choice(["lime white", "yellow ochre", "carbon black"])),
                  thickness=rng.uniform(0.8, 2.0) * k)
    # figurative shapes in the main field
    field_h = field_bottom - field_top
    if field_h > 20:
        n_fig = int(rng.poisson(width_mm * field_h / 9000.0)) + 1
        for _ in range(n_fig):
            cx = rng.uniform(0, width_mm)
            cy = rng.uniform(field_top + 10, field_bottom - 10)
            lo = min(12.0, field_h / 3)
            r0 = rng.uniform(lo, max(lo + 1.0, min(70.0, field_h / 2)))
            pts = _blob(rng, cx, cy, r0)
            fill = col(rng.choice(["red ochre", "egyptian blue", "yellow ochre", "green earth", "pink", "cinnabar"]))
            _poly(img, pts * k, fill)
            _poly(img, pts * k, col("carbon black"), thickness=rng.uniform(0.5, 1.5) * k)
            if rng.random() < 0.6:
                incisions.append(pts)
            # a stem or wing stroke
            t = np.linspace(0, 1, 30)[:, None]
            end = np.array([cx, cy]) + rng.normal(0, r0, 2) * 1.5
            ctrl = np.array([cx, cy]) + rng.normal(0, r0, 2)
            stem = (1 - t) ** 2 * np.array([cx, cy]) + 2 * t * (1 - t) * ctrl + t ** 2 * end
            _poly(img, stem * k, fill, closed=False, thickness=rng.uniform(1.5, 4) * k)
        # rosettes: a ring of dots around a dot
        for _ in range(int(rng.poisson(width_mm * field_h / 30000.0))):
            cx, cy = rng.uniform(0, width_mm), rng.uniform(field_top + 8, field_bottom - 8)
            rr, n_pet = rng.uniform(4, 12), int(rng.integers(6, 11))
            colour = col(rng.choice(["red ochre", "egyptian blue", "carbon black", "cinnabar"]))
            dot = max(1, int(round(rr * 0.3 * k)))
            cv2.circle(img, (int(cx * k), int(cy * k)), dot, colour, -1, cv2.LINE_AA)
            for a in np.linspace(0, 2 * np.pi, n_pet, endpoint=False):
                cv2.circle(img, (int((cx + rr * np.cos(a)) * k), int((cy + rr * np.sin(a)) * k)), dot, colour, -1,
                           cv2.LINE_AA)
    # spiral frieze
    if frieze_h:
        y0 = top
        ground_name = rng.choice(["lime white", "egyptian blue", "yellow ochre"])
        hband(y0, y0 + frieze_h, ground_name)
        cy = y0 + frieze_h / 2
        r = frieze_h * 0.38
        step = 2.2 * r
        colour = col(rng.choice([c for c in ("red ochre", "carbon black", "egyptian blue") if c != ground_name]))
        for i, cx in enumerate(np.arange(rng.uniform(0, step), width_mm + step, step)):
            sp = _spiral(cx, cy, r, rng.uniform(1.7, 2.4), rng.uniform(0, 2 * np.pi), 1 if i % 2 else -1)
            _poly(img, sp * k, colour, closed=False, thickness=max(frieze_h * 0.06, 1.0) * k)
            if i % 2 == 0:
                incisions.append(sp)
            # the tangent link to the next spiral
            link = np.array([[cx, cy + r * (1 if i % 2 else -1)], [cx + step, cy - r * (1 if i % 2 else -1)]])
            _poly(img, link * k, colour, closed=False, thickness=max(frieze_h * 0.05, 1.0) * k)
        band_stack(y0)
    # a few free layout strings (not on colour boundaries), e.g. abandoned guide lines
    for _ in range(rng.integers(0, 3)):
        a = rng.uniform(0, np.pi)
        p = np.array([rng.uniform(0, width_mm), rng.uniform(0, height_mm)])
        d = np.array([np.cos(a), np.sin(a)]) * (width_mm + height_mm)
        strings.append((tuple(p - d), tuple(p + d)))
    # mottling of the paint (uneven brushing, pigment density) and fine speckle
    G = np.array([[res_mm, 0.0, 0.0], [0.0, res_mm, 0.0]])
    mott = FractalField(rng, 40.0, octaves=4, persistence=0.6, amplitude=0.025)
    shared = FractalField(rng, 25.0, octaves=4, persistence=0.6, amplitude=0.04).grid(G, (H, W))
    for c in range(3):
        img[..., c] *= 1.0 + shared + mott.grid(G + [[0, 0, 97.0 * c], [0, 0, 0]], (H, W))
    img *= 1.0 + FractalField(rng, 2.0, octaves=2, amplitude=0.02).grid(G, (H, W))[..., None]
    np.clip(img, 0.0, 1.0, out=img)
    return Painting(img, float(res_mm), strings, incisions)


def painting_from_image(image: np.ndarray, width_mm: float, *, res_mm: float = 0.25,
                        linear: bool = False) -> Painting:
    """Use a user-supplied picture as the painted layer.

    Parameters
    ----------
    image : (H, W, 3) array
        RGB picture, uint8/uint16 or float in [0, 1]; sRGB unless ``linear``.
    width_mm : float
        Physical width of the wall the picture covers; the height follows the aspect ratio.
    res_mm : float
        Raster pixel size in mm.
    linear : bool
        True if the picture is already linear RGB.

    Returns
    -------
    Painting
        With no string lines or incisions (the relief then carries grain and strokes only).
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"image must be (H, W, 3) RGB, got shape {image.shape}")
    if width_mm <= 0:
        raise ValueError(f"width_mm must be positive, got {width_mm}")
    img = image[..., :3].astype(np.float32)
    if image.dtype == np.uint8:
        img /= 255.0
    elif image.dtype == np.uint16:
        img /= 65535.0
    if not linear:  # sRGB -> linear
        img = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4).astype(np.float32)
    W = int(np.ceil(width_mm / res_mm))
    H = int(np.ceil(width_mm * image.shape[0] / image.shape[1] / res_mm))
    img = cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA if W < image.shape[1] else cv2.INTER_CUBIC)
    return Painting(np.clip(img, 0, 1).astype(np.float32), float(res_mm))
