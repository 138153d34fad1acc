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


def make_gallery(data: Path, out: Path, *, subjects=None) -> Path:
    """Render every gallery style and every shipped recipe on every available subject."""
    from common.render.enhance import relief_scale_px

    pictures = out / "gallery"
    pictures.mkdir(parents=True, exist_ok=True)
    for old in pictures.glob("*.png"):
        old.unlink()
    rows, failed, noise = {}, {}, {}
    for name in subjects or DEFAULT_SUBJECTS:
        try:
            image = _downsample(SUBJECTS[name](data), MAX_SIDE)
        except Exception as exc:  # a missing data set or solver must not stop the others
            log.warning("gallery subject %s unavailable: %s", name, exc)
            failed[name] = f"{type(exc).__name__}: {exc}"
            continue
        rows[name] = image
        noise[name] = relief_scale_px(image.normals, image.dpi, image.mask)
    crops = {name: _crop_window(image) for name, image in rows.items()}
    compare = {name: (render(image, "raking").rgb, render(image, "normal_unsharp").rgb)
               for name, image in rows.items()}
    recipes = {s: style_recipe(s, **p) for s, p in GALLERY_STYLES.items()}
    recipes.update({f"recipe-{p.stem}": load_recipe(p) for p in sorted(RECIPE_DIR.glob("*.toml"))})
    figures = {}
    for key, recipe in recipes.items():
        log.info("drawing %s", key)
        sheet_rows = []
        for name, image in rows.items():
            drawn = render(image, recipe).rgb
            figures[(key, name)] = _tone(drawn, image.mask)
            win = crops[name]
            sheet_rows.append(_row(drawn, [drawn[win], compare[name][0][win], compare[name][1][win]]))
        sheet = np.round(np.clip(_stack(sheet_rows), 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(pictures / f"{key}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    _write_markdown(out / "gallery.md", rows, recipes, failed, figures, noise)
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


HEAD = """# Illustration gallery (§7.3)

Every style and every shipped recipe (`configs/recipes/`) drawn **with its defaults** on real captures
by `python -m common.render.gallery` (regenerate after changing a style): each picture shows the style
beside raking light and RTIViewer-style normal unsharp masking, with 1:1 crops.

Draw your own:

```sh
tessera render --list-styles                                # styles, parameters, their meaning
tessera render front.h5 -o front.png --recipe default       # colour plus relief (the service's default)
tessera render front.h5 --style raking -o raking.tif --bits 16
tessera render --normals N.png --albedo A.png --dpi 600 --style ridges_valleys -p valleys=false -o r.png
```

Readable by default: every style picks its exposure and contrast from robust percentiles of what it
draws (the 5th and 95th percentiles land at 0.2 and 0.8 of the tone range through an S-curve whose
tails roll off, so a pixel saturates only ~4.5 half-ranges out; colour is exposed on its CIELAB
lightness, hue and chroma kept), its smoothing from the noise of the normal map (Immerkær's estimator;
8x8 JPEG blocks of the source images detected and smoothed over) and from the dpi, and lights a
near-flat surface (a painting, a relief) relative to its own slow undulation. `tessera render` logs
the values it chose (and the noise evidence); written back into a recipe they fix the picture.

Any size: an image above 16 Mpx is drawn in overlapping tiles (the halo covers 4 sigma of the
widest filter, line lengths and shadows) that share the exposure chosen on a central calibration
window of <= 4 Mpx; tiled and whole drawings agree within 1/255 (`tests/render/test_tiles.py`). The
renderer service reads a large face window by window from its HDF5 artifact. A recipe with a
`[segmentation]` section is tiled too: the segments are found first for the whole image, window by
window (`segment_source`: SLIC superpixels in 2048-px windows read with a blur halo, merged across the
windows' seams on one Felzenszwalb-Huttenlocher graph; the labels are identical to the in-memory
`segment_rgbn`'s, `tests/rgbn/test_segmentation.py`), kept as 4 bytes a pixel, and every tile is drawn
with its window of them. Output is 8 or 16 bit (`bits` / `--bits`); the computation is float32
throughout.

Inputs are checked: `--convention auto` (the default) reads a normal map both ways and keeps the
reading whose curl (`dp/dy - dq/dx` of the gradient field) is smaller, logging both medians and their
ratio (undecided below 1.2: OpenGL assumed and said so); a file that does not decode to unit vectors
facing the viewer (a photograph, an albedo) is refused with the share that failed.
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


def _write_markdown(path: Path, rows: dict, recipes: dict, failed: dict, figures: dict, noise: dict) -> None:
    lines = [HEAD.rstrip(), "", _recipe_reference().rstrip(), ""]
    measured = path.parent / "gallery" / "measured.md"
    if measured.is_file():
        lines += [measured.read_text().rstrip(), ""]
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
        what = recipe.description if key.startswith("recipe-") else STYLES[key].doc.splitlines()[0]
        lines += [f"### {key}", "", what,
                  "", f"![{key}: {', '.join(rows)}; style, raking, unsharp masking crops](gallery/{key}.png)", "",
                  "```toml", recipe_to_toml(recipe).rstrip(), "```", ""]
    path.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    data_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[3] / "shared" / "data"
    out_dir = Path(sys.argv[2]) if len(sys.argv) > 2 else Path(__file__).resolve().parents[2] / "docs"
    print(make_gallery(data_dir, out_dir))
