"""The illustration gallery on real data (``docs/gallery.md``, ``docs/gallery/*.png``).

Run ``python -m common.render.gallery [DATA_DIR] [OUT_DIR]``; it reads ``../shared/data`` by
default and writes one PNG per style and per shipped recipe, plus the markdown page with the tone
range each picture uses. Every row of a picture is one subject: the style at reduced size, then
three 1:1 crops of the same window — the style, raking light, and RTIViewer-style normal unsharp
masking — so a reader compares them pixel for pixel. Subjects:

* ``door``, ``canvas``, ``clay`` — the three RealRTI captures (``realrti-dev/item1``, ``item5``,
  ``item8``: a painted wooden door, a canvas painting, a shell relief in clay), solved by the
  hand-held photometric stereo (:func:`common.acquisition.handheld.handheld_rgbn`, robust solver)
  with the lights of their ``dirs.lp`` and the whole frame as the object (they fill it);
* ``coin`` — the flatbed coin's four registered scans solved with the flatbed photometric stereo
  (:func:`common.acquisition.flatbed_normals.solve_normals`) under a *nominal* lamp model
  (:data:`COIN_NOMINAL_LAMP`), because the data set comes without a calibration;
* ``cat``, ``owl``, ``ball`` (``SUBJECTS``; not drawn by default to keep the pages small) — the
  psm-seitz objects and the DiLiGenT ball's ground truth.

Beside them, one *judgement sheet* per subject (``docs/gallery/judgement_<subject>.png``,
:func:`judgement_sheet`): the defaults (the ``default`` recipe) in the first column, RTIViewer-style
normal unsharp masking and raking light beside, each column labelled; the whole subject reduced,
then two 1:1 crops — the window with the most relief and the one with the darkest colour — so a
conservator judges relief, colour and noise pixel for pixel. ``python -m common.render.gallery
--judgement`` draws only these.

The physical scales (dpi) are nominal: none of these captures records one.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import cv2
import numpy as np

from common.render.recipes import RECIPE_DIR, STYLES, load_recipe, recipe_to_toml, render, style_recipe
from common.rgbn.image import RGBNImage

log = logging.getLogger(__name__)

#: Lamp model of eq. 3.4 assumed for the uncalibrated flatbed coin: light from the scan head's
#: side (+y) at about 45 degrees, no constant term.
COIN_NOMINAL_LAMP = np.array([0.0, 0.55, 0.55, 0.0])
#: Longest side of a subject as rendered, pixels (the illustrations are drawn at this size).
MAX_SIDE = 640
#: Height of the reduced view in the gallery sheets, pixels.
TILE_HEIGHT = 128
#: Side of the 1:1 crops, pixels.
CROP = 112

# per-style parameters for the gallery: none — every style at its defaults, as a new user sees it
GALLERY_STYLES = {name: {} for name in (
    "albedo", "colour_relief", "normal_unsharp", "specular", "raking", "lambertian", "exaggerated", "toon",
    "gooch", "watercolour", "mean_curvature", "multiscale_mean_curvature", "ridges_valleys", "suggestive_contours",
    "suggestive_contours_object", "discontinuity_lines", "discontinuity_shadows", "normals")}


def _downsample(image: RGBNImage, max_side: int) -> RGBNImage:
    h, w = image.shape
    f = max(h, w) / max_side
    if f <= 1:
        return image
    size = (int(round(w / f)), int(round(h / f)))
    n = cv2.resize(image.normals, size, interpolation=cv2.INTER_AREA)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    d = None if image.discontinuity is None else cv2.resize(image.discontinuity, size, interpolation=cv2.INTER_AREA)
    return RGBNImage(albedo=cv2.resize(image.albedo, size, interpolation=cv2.INTER_AREA),
                     mask=cv2.resize(image.mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0,
                     dpi=image.dpi / f, normals=n, discontinuity=d)


def rti(data: Path, item: str) -> RGBNImage:
    """A RealRTI capture solved from its JPEGs and ``dirs.lp`` (sRGB decoded, whole frame)."""
    from common.acquisition.handheld import handheld_rgbn, read_images
    from common.acquisition.lightfile import read_lights

    d = data / "realrti-dev" / item
    lights = read_lights(d / "dirs.lp")
    files = [d / name for name in lights.filenames] if lights.filenames else sorted(d.glob("*.jpg"))
    images, saturated = read_images(files, srgb=True)
    mask = np.ones(images.shape[1:3], bool)
    return handheld_rgbn(images, lights, mask=mask, saturated=saturated, dpi=96.0, discontinuities=True)


def ball(data: Path) -> RGBNImage:
    d = data / "diligent-ball"
    n = np.load(d / "normal_gt.npy").astype(np.float32)
    mask = cv2.imread(str(d / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    n[~mask] = (0, 0, 1)
    return RGBNImage(albedo=np.full(n.shape, 0.75, np.float32), mask=mask, dpi=200.0, normals=n)


def seitz(data: Path, name: str) -> RGBNImage:
    from common.acquisition.handheld import handheld_rgbn, read_images, read_mask, sphere_lights
    from common.acquisition.spheres import find_sphere

    d = data / "psm-seitz"
    files = lambda obj: sorted((d / obj).glob(f"{obj}.[0-9][0-9].png"))  # noqa: E731
    images, saturated = read_images(files(name))
    chrome, _ = read_images(files("chrome"))
    grey, grey_sat = read_images(files("gray"))
    chrome_circle = find_sphere(read_mask(d / "chrome" / "chrome.mask.png"))
    grey_circle = find_sphere(read_mask(d / "gray" / "gray.mask.png"))
    lights = sphere_lights(chrome, chrome_circle, diffuse_images=grey, diffuse_circle=grey_circle,
                           diffuse_saturated=grey_sat)
    mask = read_mask(d / name / f"{name}.mask.png", images.shape[1:3])
    img = handheld_rgbn(images, lights, mask=mask, saturated=saturated, dpi=100.0, discontinuities=True)
    img.albedo = np.clip(img.albedo / max(float(np.percentile(img.albedo[img.mask], 99)), 1e-6), 0, 1)
    return img


def coin(data: Path) -> RGBNImage:
    from common.acquisition.flatbed_normals import solve_normals
    from common.acquisition.locate import to_float

    d = data / "flatbed-coin"
    scans = []
    for angle in (0, 90, 180, 270):
        raw = cv2.imread(str(d / f"registered_{angle}.png"), cv2.IMREAD_UNCHANGED)
        rgb = cv2.cvtColor(raw[..., :3], cv2.COLOR_BGR2RGB)
        scans.append(rgb)
    # the gallery does not need 1600 px: solve at a quarter of the size
    small = [cv2.resize(s, (s.shape[1] // 4, s.shape[0] // 4), interpolation=cv2.INTER_AREA) for s in scans]
    dpi = 1600.0 / 4
    images = np.stack([to_float(s) for s in small])
    mask = _coin_mask(small[0])
    img = solve_normals(images, [0.0, 90.0, 180.0, 270.0], COIN_NOMINAL_LAMP, mask=mask, dpi=dpi)
    img.albedo = np.clip(0.6 * img.albedo / max(float(np.percentile(img.albedo[img.mask], 99)), 1e-6), 0, 1)
    return img


def _coin_mask(rgb: np.ndarray) -> np.ndarray:
    # the coin lies on a checkerboard, which defeats background subtraction: take the largest
    # circle (the coin is a rounded decagon filling most of the crop), shrunk to stay on the metal
    grey = cv2.GaussianBlur(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), (0, 0), 2)
    h, w = grey.shape
    circles = cv2.HoughCircles(grey, cv2.HOUGH_GRADIENT, dp=1, minDist=w, param1=80, param2=30,
                               minRadius=int(0.38 * min(h, w)), maxRadius=int(0.5 * min(h, w)))
    if circles is None:
        raise ValueError("coin outline not found")
    cx, cy, r = circles[0, 0]
    rows, cols = np.mgrid[0:h, 0:w]
    return (cols - cx) ** 2 + (rows - cy) ** 2 < (0.95 * r) ** 2


SUBJECTS = {"door": lambda d: rti(d, "item1"), "canvas": lambda d: rti(d, "item5"), "clay": lambda d: rti(d, "item8"),
            "coin": coin, "cat": lambda d: seitz(d, "cat"), "owl": lambda d: seitz(d, "owl"), "ball": ball}
#: Drawn by default (the pages stay small): the real relief a conservator works on.
DEFAULT_SUBJECTS = ("door", "canvas", "clay", "coin")
ABOUT = {
    "door": "RealRTI *item1*, a painted wooden door: 60 dome-light JPEGs (487x439) solved by robust hand-held "
            "photometric stereo with the lights of its `dirs.lp`, nominal 96 dpi. The dome's near lights tilt "
            "the solved normals slowly across the frame; styles that light the surface level it first.",
    "canvas": "RealRTI *item5*, a canvas painting: 49 hand-held-light JPEGs (334x322), solved the same way; its "
              "normal map carries 8x8 JPEG blocks (measured 1.57x, see the noise evidence below).",
    "clay": "RealRTI *item8*, a shell relief in clay: 48 dome-light JPEGs (362x301), solved the same way.",
    "coin": "flatbed-coin: four registered scans (0/90/180/270°) solved by the flatbed photometric stereo "
            "(§3.3.6) at 1/4 size under a *nominal* lamp model a = (0, 0.55, 0.55, 0) — the data set has no "
            "calibration, so the relief depth is only indicative.",
    "cat": "psm-seitz *cat*: 12 flash images, lights from the chrome sphere, nominal 100 dpi.",
    "owl": "psm-seitz *owl*, solved as the cat.",
    "ball": "DiLiGenT *ball*, ground-truth normals, grey albedo, nominal 200 dpi.",
}


def load_subjects(data: Path, subjects=None) -> tuple[dict, dict]:
    """The subjects solved from ``data`` and reduced to :data:`MAX_SIDE`: ({name: image},
    {name: why it could not be drawn})."""
    rows, failed = {}, {}
    for name in subjects or DEFAULT_SUBJECTS:
        try:
            rows[name] = _downsample(SUBJECTS[name](data), MAX_SIDE)
        except Exception as exc:  # a missing data set or solver must not stop the others
            log.warning("gallery subject %s unavailable: %s", name, exc)
            failed[name] = f"{type(exc).__name__}: {exc}"
    return rows, failed


def make_gallery(data: Path, out: Path, *, subjects=None) -> Path:
    """Render every gallery style and every shipped recipe on every available subject, and the
    judgement sheets (:func:`make_judgement`)."""
    from common.render.enhance import relief_scale_px

    pictures = out / "gallery"
    pictures.mkdir(parents=True, exist_ok=True)
    for old in pictures.glob("*.png"):
        old.unlink()
    rows, failed = load_subjects(data, subjects)
    noise = {name: relief_scale_px(image.normals, image.dpi, image.mask) for name, image in rows.items()}
    crops = {name: _crop_window(image) for name, image in rows.items()}
    compare = {name: (render(image, "raking").rgb, render(image, "normal_unsharp").rgb)
               for name, image in rows.items()}
    recipes = {s: style_recipe(s, **p) for s, p in GALLERY_STYLES.items()}
    recipes.update({f"recipe-{p.stem}": load_recipe(p) for p in sorted(RECIPE_DIR.glob("*.toml"))})
    figures = {}
    judged = {name: {"raking": compare[name][0], "normal_unsharp": compare[name][1]} for name in rows}
    for key, recipe in recipes.items():
        log.info("drawing %s", key)
        sheet_rows = []
        for name, image in rows.items():
            drawn = render(image, recipe).rgb
            if key == "recipe-default":
                judged[name]["default"] = drawn
            figures[(key, name)] = _tone(drawn, image.mask)
            win = crops[name]
            sheet_rows.append(_row(drawn, [drawn[win], compare[name][0][win], compare[name][1][win]]))
        sheet = np.round(np.clip(_stack(sheet_rows), 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(pictures / f"{key}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    log.info("drawing the judgement sheets")
    judgement = make_judgement(rows, pictures, judged)
    _write_markdown(out / "gallery.md", rows, recipes, failed, figures, noise, judgement)
    return out / "gallery.md"


def _crop_window(image: RGBNImage) -> tuple:
    """The CROP x CROP window with the most relief (variance of the normals' x and y), 1:1."""
    h, w = image.shape
    c = min(CROP, h, w)
    dx = np.abs(np.diff(image.normals[..., :2], axis=1)).sum(axis=2)
    energy = cv2.boxFilter(np.pad(dx, ((0, 0), (0, 1))), -1, (c, c), normalize=True, borderType=cv2.BORDER_CONSTANT)
    energy[~image.mask] = 0
    half = c // 2
    inner = np.zeros_like(energy)
    inner[half:h - half, half:w - half] = energy[half:h - half, half:w - half]
    r, col = np.unravel_index(int(np.argmax(inner)), inner.shape)
    r0, c0 = int(np.clip(r - half, 0, h - c)), int(np.clip(col - half, 0, w - c))
    return (slice(r0, r0 + c), slice(c0, c0 + c))


def _tone(rgb: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(5th-95th percentile span of the luminance, share of pixels with a channel at 0 or 255)."""
    q = np.round(np.clip(rgb, 0, 1) * 255)[mask]
    lum = q @ np.array([0.2126, 0.7152, 0.0722])
    p5, p95 = np.percentile(lum, [5, 95]) if lum.size else (0, 0)
    return float((p95 - p5) / 255), float(np.mean((q.max(axis=1) >= 255) | (q.min(axis=1) <= 0))) if lum.size else 0.0


def _row(full: np.ndarray, crops: list, height: int = TILE_HEIGHT, gap: int = 4) -> np.ndarray:
    """The reduced view, then the 1:1 crops (top-aligned), white gaps between."""
    w = max(1, int(round(full.shape[1] * height / full.shape[0])))
    h = max(height, max(c.shape[0] for c in crops))
    parts = [cv2.resize(full, (w, height), interpolation=cv2.INTER_AREA)]
    parts += [np.asarray(c, np.float32) for c in crops]
    out = []
    for p in parts:
        pad = np.ones((h, p.shape[1], 3), np.float32)
        pad[:p.shape[0]] = p
        out += [pad, np.ones((h, gap, 3), np.float32)]
    return np.concatenate(out[:-1], axis=1)


def _stack(rows: list, gap: int = 6) -> np.ndarray:
    if not rows:
        return np.ones((TILE_HEIGHT, TILE_HEIGHT, 3), np.float32)
    w = max(r.shape[1] for r in rows)
    out = []
    for r in rows:
        pad = np.ones((r.shape[0], w, 3), np.float32)
        pad[:, :r.shape[1]] = r
        out += [pad, np.ones((gap, w, 3), np.float32)]
    return np.concatenate(out[:-1], axis=0)


#: The judgement sheets' columns: (label, recipe or style) — the defaults first, then what a
#: conservator would otherwise use (RTIViewer's enhancement, raking light), all at their defaults.
JUDGEMENT_COLUMNS = (("default recipe (Tessera's defaults)", "default"),
                     ("RTIViewer-style unsharp masking (gain 3, 1 mm)", "normal_unsharp"),
                     ("raking light (12 deg, levelled)", "raking"))
#: Size of the judgement sheets' 1:1 crops (height, width), pixels.
JUDGEMENT_CROP = (160, 240)


def _window(score: np.ndarray, mask: np.ndarray, size: tuple, *, best=np.argmax, away_from=None) -> tuple:
    """The (rows, cols) slices of the ``size`` window, fully inside the image, whose mean ``score``
    over the fragment is the best (``np.argmax`` or ``np.argmin``); windows less than 90 % on the
    fragment are not considered, nor (when another is left) windows overlapping the window
    ``away_from`` by more than a quarter of their area."""
    h, w = mask.shape
    ch, cw = min(size[0], h), min(size[1], w)
    m = mask.astype(np.float32)
    total = cv2.boxFilter(np.where(mask, score, 0).astype(np.float32), -1, (cw, ch), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)
    cover = cv2.boxFilter(m, -1, (cw, ch), normalize=False, borderType=cv2.BORDER_CONSTANT)
    mean = total / np.maximum(cover, 1.0)
    # box centres whose window lies inside the image and on the fragment
    ok = np.zeros((h, w), bool)
    ok[ch // 2:h - (ch - 1) // 2, cw // 2:w - (cw - 1) // 2] = True
    ok &= cover >= 0.9 * ch * cw
    if not ok.any():
        ok[ch // 2:h - (ch - 1) // 2, cw // 2:w - (cw - 1) // 2] = True
    if away_from is not None:
        rows, cols = np.arange(h)[:, None] - ch // 2, np.arange(w)[None, :] - cw // 2   # window origins
        dr = np.clip(ch - np.abs(rows - away_from[0].start), 0, None)
        dc = np.clip(cw - np.abs(cols - away_from[1].start), 0, None)
        apart = ok & (dr * dc <= 0.25 * ch * cw)
        if apart.any():
            ok = apart
    mean = np.where(ok, mean, np.nan)
    r, c = np.unravel_index(int(np.nanargmax(mean) if best is np.argmax else np.nanargmin(mean)), mean.shape)
    r0, c0 = int(np.clip(r - ch // 2, 0, h - ch)), int(np.clip(c - cw // 2, 0, w - cw))
    return (slice(r0, r0 + ch), slice(c0, c0 + cw))


def judgement_windows(image: RGBNImage) -> dict:
    """The judgement sheet's two 1:1 windows: ``"most relief"`` (largest mean change of the normals
    between neighbouring pixels) and ``"darkest colour"`` (lowest mean albedo luminance, overlapping
    the first by at most a quarter where the subject leaves room)."""
    dx = np.abs(np.diff(image.normals[..., :2], axis=1, append=image.normals[:, -1:, :2])).sum(axis=2)
    dy = np.abs(np.diff(image.normals[..., :2], axis=0, append=image.normals[-1:, :, :2])).sum(axis=2)
    lum = image.albedo @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    relief = _window(dx + dy, image.mask, JUDGEMENT_CROP)
    return {"most relief": relief,
            "darkest colour": _window(lum, image.mask, JUDGEMENT_CROP, best=np.argmin, away_from=relief)}


def _text(canvas: np.ndarray, text: str, x: int, y: int, scale: float = 0.45, bold: bool = False) -> None:
    """Black text, baseline at ``y`` (an (H, W, 3) uint8 image, in place)."""
    cv2.putText(canvas, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0),
                2 if bold else 1, cv2.LINE_AA)


def judgement_sheet(name: str, image: RGBNImage, drawn: dict | None = None) -> tuple[np.ndarray, dict]:
    """One subject's judgement sheet: a column per :data:`JUDGEMENT_COLUMNS` entry, labelled on
    top; rows: the whole subject reduced to the column width, then the windows of
    :func:`judgement_windows` at 1:1, each row labelled on the left. ``drawn`` maps a column's
    recipe to its rendering (drawn here when missing). Returns the sheet (8-bit RGB) and per
    column the figures of :func:`judgement_figures`."""
    drawn = dict(drawn or {})
    for _, recipe in JUDGEMENT_COLUMNS:
        if recipe not in drawn:
            drawn[recipe] = render(image, recipe).rgb
    wins = judgement_windows(image)
    h, w = image.shape
    col_w = max(JUDGEMENT_CROP[1], 320)
    scale = min(1.0, col_w / w)
    whole_h = max(1, int(round(h * scale)))
    left, gap, head, title_h = 150, 8, 40, 30
    marks = dict(zip(wins, "AB"))
    rows = [(f"whole ({100 * scale:.0f} %)", None, whole_h)] + [(f"{marks[k]}: {k}, 1:1", win, win[0].stop - win[0].start)
                                                               for k, win in wins.items()]
    height = title_h + head + sum(r[2] + gap for r in rows)
    width = left + len(JUDGEMENT_COLUMNS) * (col_w + gap)
    sheet = np.full((height, width, 3), 255, np.uint8)
    _text(sheet, f"{name}: the defaults judged against RTIViewer-style enhancement and raking light "
                 f"({w} x {h} px, crops at 1:1)", 8, 20, 0.5, bold=True)
    figures = {}
    for j, (label, recipe) in enumerate(JUDGEMENT_COLUMNS):
        x = left + j * (col_w + gap)
        words, line, y = label.split(), "", title_h + 16
        for word in words:   # wrap the label over two lines at the column width
            trial = (line + " " + word).strip()
            if cv2.getTextSize(trial, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)[0][0] > col_w and line:
                _text(sheet, line, x, y)
                line, y = word, y + 16
            else:
                line = trial
        _text(sheet, line, x, y)
        rgb = np.round(np.clip(drawn[recipe], 0.0, 1.0) * 255).astype(np.uint8)
        figures[label] = judgement_figures(drawn[recipe], image.mask)
        y = title_h + head
        for row_label, win, rh in rows:
            if win is None:   # the whole, with the windows A and B outlined
                part = cv2.resize(rgb, (int(round(w * scale)), whole_h), interpolation=cv2.INTER_AREA)
                for key, (rs, cs) in wins.items():
                    p0 = (int(cs.start * scale), int(rs.start * scale))
                    p1 = (int((cs.stop - 1) * scale), int((rs.stop - 1) * scale))
                    cv2.rectangle(part, p0, p1, (255, 0, 255), 1, cv2.LINE_AA)
                    cv2.putText(part, marks[key], (p0[0] + 3, p0[1] + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45,
                                (255, 0, 255), 1, cv2.LINE_AA)
            else:
                part = rgb[win]
            sheet[y:y + part.shape[0], x:x + part.shape[1]] = part
            if j == 0:
                _text(sheet, row_label, 8, y + 16)
                if win is not None:
                    _text(sheet, f"rows {win[0].start}-{win[0].stop}", 8, y + 34, 0.4)
                    _text(sheet, f"cols {win[1].start}-{win[1].stop}", 8, y + 50, 0.4)
            y += rh + gap
    return sheet, figures


def judgement_figures(rgb: np.ndarray, mask: np.ndarray) -> dict:
    """What the judgement table reports of a drawing on the fragment: median luminance (0-255),
    the 5th-95th percentile span of the luminance (share of the range) and the median HSV
    saturation (0-255)."""
    q = np.round(np.clip(rgb, 0, 1) * 255).astype(np.uint8)
    lum = (q.astype(np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32))[mask]
    sat = cv2.cvtColor(q, cv2.COLOR_RGB2HSV)[..., 1][mask]
    if lum.size == 0:
        return {"median": 0.0, "span": 0.0, "saturation": 0.0}
    p5, p95 = np.percentile(lum, [5, 95])
    return {"median": float(np.median(lum)), "span": float((p95 - p5) / 255), "saturation": float(np.median(sat))}


def make_judgement(rows: dict, pictures: Path, drawn: dict | None = None) -> dict:
    """Write ``judgement_<subject>.png`` for every subject of ``rows`` into ``pictures``; returns
    {subject: {column label: figures}}."""
    out = {}
    for name, image in rows.items():
        sheet, out[name] = judgement_sheet(name, image, (drawn or {}).get(name))
        cv2.imwrite(str(pictures / f"judgement_{name}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return out


HEAD = """# Illustration gallery (§7.3)

Every style and every shipped recipe (`configs/recipes/`) drawn **with its defaults** on real captures
by `python -m common.render.gallery` (regenerate after changing a style; it reads `../shared/data`
and rewrites this page and `docs/gallery/`): each picture shows the style beside raking light and
RTIViewer-style normal unsharp masking, with 1:1 crops; the labelled judgement sheets (below) put the
defaults beside RTIViewer-style enhancement and raking light (`python -m common.render.gallery
--judgement` redraws only those).

Draw your own:

```sh
tessera render --list-styles                                # styles, parameters, their meaning
tessera render front.h5 -o front.png --recipe default       # colour plus relief (the service's default: [services.renderer] recipe)
tessera render front.h5 --style raking -o raking.tif --bits 16
tessera render --normals N.png --albedo A.png --dpi 600 --style ridges_valleys -p valleys=false -o r.png
```

Readable by default: every style picks its exposure and contrast from robust percentiles of what it
draws (the 5th and 95th percentiles land at 0.2 and 0.8 of the tone range through an S-curve whose
tails roll off, so a pixel saturates only ~4.5 half-ranges out; colour is exposed on its CIELAB
lightness, hue and chroma kept — a colour varying less than 15 L* is stretched as it is unless that is
under 6 L* or 10 times the pixel noise of its lightness, so one metal or one plaster uses the range but
noise is drawn at most ~6 L* strong; specular enhancement and watercolour also expose the lightness of
what they drew), its smoothing from the noise of the normal map (Immerkær's estimator;
8x8 JPEG blocks of the source images detected and smoothed over) and from the dpi, and lights a
near-flat surface (a painting, a relief) relative to its own slow undulation. `tessera render` logs
the values it chose (and the noise evidence); written back into a recipe they fix the picture.
Relief and exposure act on CIELAB lightness; a colour they would push outside sRGB keeps its
lightness and hue and loses chroma only, down to the largest chroma sRGB can show there
(`enhance.gamut_map_lab`, by bisection; OpenCV's float Lab->RGB, which clips each channel and so
turns the hue, is used only for the colours inside the gamut). The web viewer's shaders do the same
(`services/web/static/viewer/common.glsl`, `tests/web/test_shader_parity.py`).

Any size: an image above 16 Mpx is drawn in overlapping tiles (the halo covers 4 sigma of the
widest filter — 3 sigma of exaggerated shading's base level, whose share of the picture keeps the
difference under 1/255 — line lengths and shadows) that share the exposure chosen on a central calibration
window of <= 4 Mpx; the coarse normal field that levelling lights a near-flat surface by (sigma up to
96 px) is computed once for the whole image, window by window, and each tile interpolates its window
of it, so its 4-sigma reach is not drawn again around every tile; tiled and whole drawings agree within
1/255 (`tests/render/test_tiles.py`). The
renderer service reads a large face window by window from its HDF5 artifact. A recipe with a
`[segmentation]` section is tiled too: the segments are found first for the whole image, window by
window (`segment_source`: SLIC superpixels in 2048-px windows read with a blur halo, found on the means
of 2x2-pixel blocks and their boundaries between unlike superpixels then placed per pixel, merged across
the windows' seams on one Felzenszwalb-Huttenlocher graph; the labels are identical to the in-memory
`segment_rgbn`'s, `tests/rgbn/test_segmentation.py`), kept as 4 bytes a pixel, and every tile is drawn
with its window of them. Output is 8 or 16 bit (`bits` / `--bits`); the computation is float32
throughout. Full-resolution smoothing, exaggerated shading's fine levels and multiscale curvature's
fine levels are computed in row strips of ~1 Mpx with a halo of the kernel's reach, so their
temporaries never have the image's size; coarser levels are taken on grids aligned to the whole
image's. The layers of a recipe share the normals they smooth at the same scale (exaggerated
shading's finest level is the noise scale discontinuity lines smooth at), and while a rendering
runs, freed arrays are reused instead of being handed back to the kernel and page-faulted in
again (`common/render/_heap.py`: the segments recipe 8-21 % less CPU time at 12 Mpx in three
paired runs on the station machine, for 120-240 MB more peak memory; per tile when tiled, so a
tile's memory is handed back before the next).

Inputs are checked: `--convention auto` (the default) reads a normal map both ways and keeps the
reading whose curl (`dp/dy - dq/dx` of the gradient field) is smaller, logging both medians and their
ratio (undecided below 1.2: OpenGL assumed and said so); a file that does not decode to unit vectors
facing the viewer (a photograph, an albedo) is refused with the share that failed.

A colour-only image (no normals) is drawn without the styles that need normals (listed in
`Rendering.skipped` and the artifact's `skipped_styles`; where no colour layer is left, the albedo as captured
(`exposure = "none"`) under the lines that are, so the default recipe draws an imported picture's own colour and
outline, not a white silhouette, nor its pale plaster stretched until a pink band turns near black), and said once:
`render()` (`tessera render`) warns `image has no normals: skipped ...` once per drawing, tiled or
not; the renderer service draws through `render_h5`, which leaves it to its caller, and logs
`fragment F face has no normals: skipped ...` once per face at INFO (a colour-only import is normal, not a fault) (`render(..., warn_skipped=False)` for a caller that
says it itself; `tests/render/test_renderer_service.py`, `tests/render/test_recipes.py`).

The figures measured now follow (the first section of `docs/gallery/measured.md`, copied here by the
gallery); that file keeps how each earlier figure was measured: [gallery/measured.md](gallery/measured.md).
"""


def _recipe_reference() -> str:
    """The recipe format and every parameter's meaning (from :data:`PARAM_DOCS`)."""
    from common.render.recipes import BLENDS, PARAM_DOCS

    lines = ["## Recipes", "",
             "A recipe is a TOML file (`--recipe FILE`, or a shipped name from `configs/recipes/`):", "",
             "```toml",
             'name = "mine"                      # shown in the artifact and logs',
             'description = "what it is for"',
             "background = [1.0, 1.0, 1.0]       # display RGB outside the fragment, 0-1 each",
             "bits = 8                           # 8 or 16 bits per channel on output",
             "",
             "[preprocess]                       # optional, once before the layers",
             "smooth_mm = 0.0                    # foreshortening-corrected Gaussian, mm (§7.2.1)",
             "bilateral = { sigma_x = 3.0, sigma_c = 0.1, sigma_n = 0.2 }   # pixels, colour, normal (eq. 7.2)",
             "",
             "[segmentation]                     # optional: colour+normal segments (§7.2.4)",
             "scale = 400.0                      # Felzenszwalb k in 1/255 units: larger = fewer segments",
             "sigma_px = 1.0                     # pre-smoothing, pixels",
             "min_size = 400                     # smallest segment, pixels",
             "colour_weight = 1.0                # weights of colour and normal differences",
             "normal_weight = 1.0",
             "",
             "[[layer]]                          # drawn in order",
             'style = "colour_relief"            # any style below; other keys are its parameters',
             'blend = "normal"                   # ' + " | ".join(BLENDS),
             "opacity = 1.0                      # 0-1",
             "# segments = [0]                   # only on these segments (0 = largest), or",
             "# exclude_segments = [0]           # everywhere but these",
             "```", "",
             "Blends: `multiply`, `screen`, `darken`, `lighten`, `overlay` and `soft_light` (W3C Compositing "
             "formulas) mix the layer's RGB with what lies below; `lightness` applies the layer's grey "
             "(0.5 = none) as relief to the CIELAB lightness below only, so the colour keeps its hue. "
             "A parameter of the wrong type is refused naming the layer, style and parameter.", "",
             "| parameter | meaning and unit | styles (default) |", "|---|---|---|"]
    by_name: dict = {}
    for style in STYLES.values():
        for k, v in style.parameters().items():
            by_name.setdefault(k, []).append(f"{style.name} ({v!r})")
    for k in sorted(by_name):
        lines.append(f"| `{k}` | {PARAM_DOCS.get(k, '').replace('|', '/')} | {', '.join(by_name[k])} |")
    return "\n".join(lines) + "\n"


def _judgement_markdown(rows: dict, judgement: dict) -> list:
    lines = ["## Judgement sheets", "",
             "One sheet per subject, `docs/gallery/judgement_<subject>.png`: the columns, labelled on the sheet, are "
             + ", ".join(f"**{label}**" for label, _ in JUDGEMENT_COLUMNS)
             + ", each at its defaults; the rows are the whole subject reduced (the windows outlined, "
             "lettered A and B), then two 1:1 windows of "
             f"{JUDGEMENT_CROP[1]} x {JUDGEMENT_CROP[0]} px — the most relief (largest change of the normals) and the "
             "darkest colour (lowest albedo luminance; overlapping the first by at most a quarter where the subject "
             "leaves room) — whose position is printed beside them. Drawn by "
             "`python -m common.render.gallery` (all pictures) or `python -m common.render.gallery --judgement` "
             "(these sheets only).", "",
             "Figures on the fragment: median luminance (0-255) / 5th-95th percentile span of the luminance / "
             "median HSV saturation (0-255).", "",
             "| subject | " + " | ".join(label for label, _ in JUDGEMENT_COLUMNS) + " |",
             "|---" * (len(JUDGEMENT_COLUMNS) + 1) + "|"]
    for name in rows:
        cells = []
        for label, _ in JUDGEMENT_COLUMNS:
            f = judgement[name][label]
            cells.append(f"{f['median']:.0f} / {100 * f['span']:.0f} % / {f['saturation']:.0f}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("")
    for name in rows:
        lines += [f"![judgement sheet, {name}: default recipe, RTIViewer-style unsharp masking, raking light]"
                  f"(gallery/judgement_{name}.png)", ""]
    return lines


def _write_markdown(path: Path, rows: dict, recipes: dict, failed: dict, figures: dict, noise: dict,
                    judgement: dict | None = None) -> None:
    lines = [HEAD.rstrip(), ""]
    measured = path.parent / "gallery" / "measured.md"
    if measured.is_file():   # its first section: the current figures (the rest is their history)
        text = measured.read_text()
        cut = text.find("\n## ", text.find("## ") + 3)
        lines += [(text if cut < 0 else text[:cut]).rstrip(), ""]
    lines += [_recipe_reference().rstrip(), ""]
    if judgement:
        lines += _judgement_markdown(rows, judgement)
    lines += ["## Subjects", ""]
    for name in rows:
        sigma, ev = noise[name]
        lines.append(f"* **{name}** — {ABOUT.get(name, '')} Noise of the normal map {ev['noise']:.4f}, "
                     f"JPEG blocks {ev['blocks']:.2f}x → smoothing {sigma:.2f} px.")
    for name, why in failed.items():
        lines.append(f"* **{name}** — not drawn: {why}")
    lines += ["", "## Tone range used (defaults)", "",
              "Share of the tone range between the 5th and 95th percentiles of the luminance on the subject, and "
              "(in brackets) the share of pixels with a channel at 0 or 255 (black ink lines count). Target: >= 50 % for every default "
              "(`python -m common.render.gallery` measures it while drawing this page).", "",
              "| style / recipe | " + " | ".join(rows) + " |", "|---" * (len(rows) + 1) + "|"]
    for key in recipes:
        cells = [f"{100 * figures[(key, n)][0]:.0f} % ({100 * figures[(key, n)][1]:.1f} %)" for n in rows]
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    lines.append("")
    lines += ["## Pictures", "",
              "Each row: one subject, reduced; then three 1:1 crops of the window with the most relief — "
              "**the style**, **raking light** (elevation 12°, levelled), **RTIViewer-style normal unsharp "
              "masking** (gain 3, 1 mm) — in that order. Rows: " + ", ".join(rows) + ".", ""]
    for key, recipe in recipes.items():
        what = recipe.description if key.startswith("recipe-") else STYLES[key].summary
        lines += [f"### {key}", "", what,
                  "", f"![{key}: {', '.join(rows)}; style, raking, unsharp masking crops](gallery/{key}.png)", "",
                  "```toml", recipe_to_toml(recipe).rstrip(), "```", ""]
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m common.render.gallery", description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="?", type=Path,
                        default=Path(__file__).resolve().parents[3] / "shared" / "data", help="the data folder")
    parser.add_argument("out", nargs="?", type=Path, default=Path(__file__).resolve().parents[2] / "docs",
                        help="where gallery.md and gallery/ are written")
    parser.add_argument("--judgement", action="store_true",
                        help="draw only the judgement sheets (gallery/judgement_<subject>.png) and print their figures")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if args.judgement:
        rows, _ = load_subjects(args.data)
        pictures = args.out / "gallery"
        pictures.mkdir(parents=True, exist_ok=True)
        print("\n".join(_judgement_markdown(rows, make_judgement(rows, pictures))))
    else:
        print(make_gallery(args.data, args.out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
