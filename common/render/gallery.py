"""The illustration gallery on real data (``docs/gallery.md``, ``docs/gallery/*.png``).

Run ``python -m common.render.gallery [DATA_DIR] [OUT_DIR]``; it reads ``../shared/data`` by
default and writes one small PNG per (subject, style) plus the markdown page. Subjects:

* ``ball`` — DiLiGenT "ball" ground-truth normals (``normal_gt.npy``; its row 0 is the top of the
  image and y points up, as in Tessera), grey albedo;
* ``cat``, ``owl`` — psm-seitz objects solved by hand-held photometric stereo
  (:func:`common.acquisition.handheld.handheld_rgbn`, robust solver) with the lights found on the
  chrome sphere and their intensities on the grey sphere;
* ``coin`` — the flatbed coin's four registered scans solved with the flatbed photometric stereo
  (:func:`common.acquisition.flatbed_normals.solve_normals`) under a *nominal* lamp model
  (:data:`COIN_NOMINAL_LAMP`), because the data set comes without a calibration.

The physical scales (dpi) are nominal too: none of these captures records one.
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
MAX_SIDE = 320
#: Height of a subject in the gallery sheets, pixels.
TILE_HEIGHT = 180

# per-style parameters for the gallery (everything else at the style defaults)
GALLERY_STYLES = {
    "albedo": {},
    "normals": {},
    "lambertian": {},
    "raking": {},
    "toon": {"levels": 3, "n_colours": 5},
    "gooch": {"colour": False},
    "exaggerated": {},
    "mean_curvature": {},
    "multiscale_mean_curvature": {},
    "discontinuity_lines": {},
    "discontinuity_shadows": {},
    "suggestive_contours": {},
    "suggestive_contours_object": {},
    "ridges_valleys": {},
    "watercolour": {},
}


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


SUBJECTS = {"ball": ball, "cat": lambda d: seitz(d, "cat"), "owl": lambda d: seitz(d, "owl"), "coin": coin}


def make_gallery(data: Path, out: Path, *, subjects=None) -> Path:
    """Render every gallery style and every shipped recipe on every available subject."""
    pictures = out / "gallery"
    pictures.mkdir(parents=True, exist_ok=True)
    rows, failed = {}, {}
    for name in subjects or SUBJECTS:
        try:
            image = _downsample(SUBJECTS[name](data), MAX_SIDE)
        except Exception as exc:  # a missing data set or solver must not stop the others
            log.warning("gallery subject %s unavailable: %s", name, exc)
            failed[name] = f"{type(exc).__name__}: {exc}"
            continue
        rows[name] = image
    recipes = {s: style_recipe(s, **p) for s, p in GALLERY_STYLES.items()}
    recipes.update({f"recipe-{p.stem}": load_recipe(p) for p in sorted(RECIPE_DIR.glob("*.toml"))})
    for key, recipe in recipes.items():
        log.info("drawing %s", key)
        tiles = [render(image, recipe).rgb for image in rows.values()]
        sheet = np.round(np.clip(_sheet(tiles), 0, 1) * 255).astype(np.uint8)
        cv2.imwrite(str(pictures / f"{key}.png"), cv2.cvtColor(sheet, cv2.COLOR_RGB2BGR),
                    [cv2.IMWRITE_PNG_COMPRESSION, 9])
    _write_markdown(out / "gallery.md", rows, recipes, failed)
    return out / "gallery.md"


def _sheet(tiles: list, height: int = TILE_HEIGHT, gap: int = 6) -> np.ndarray:
    """Tiles side by side at a common height, separated by white gaps."""
    parts = []
    for t in tiles:
        w = max(1, int(round(t.shape[1] * height / t.shape[0])))
        parts += [cv2.resize(t, (w, height), interpolation=cv2.INTER_AREA), np.ones((height, gap, 3), np.float32)]
    return np.concatenate(parts[:-1], axis=1) if parts else np.ones((height, height, 3), np.float32)


def _write_markdown(path: Path, rows: dict, recipes: dict, failed: dict) -> None:
    lines = ["# Illustration gallery (§7.3)", "",
             "Every style and every shipped recipe (`configs/recipes/`) drawn on real data by "
             "`python -m common.render.gallery` (regenerate after changing a style). Under each picture is "
             "the recipe that drew it.", "",
             "Draw your own:", "",
             "```sh",
             "tessera render --list-styles                               # styles and their parameters",
             "tessera render front.h5 --style exaggerated -o front.png  # an RGBN artifact, one style",
             "tessera render front.h5 --recipe relief -o front.tif --bits 16",
             "tessera render --normals N.png --albedo A.png --convention directx --dpi 600 \\",
             "    --style toon -p levels=4 -o toon.png                    # a normal map from another tool",
             "```", "",
             "The renderer service draws every new face with the recipe named in the station config "
             "(`[services.renderer] recipe = \"default\"`, a shipped name or a TOML path) and publishes "
             "`render.ready`; the recipe format is documented in `common/render/recipes.py`.", "",
             "Each picture shows, left to right: " + ", ".join(rows) + ". Subjects (pixel sizes are nominal — "
             "none of these captures records a scale):", ""]
    about = {
        "ball": "DiLiGenT *ball*, ground-truth normals (`normal_gt.npy`, row 0 = top, y up), grey albedo, nominal 200 dpi.",
        "cat": "psm-seitz *cat*: 12 flash images solved by robust hand-held photometric stereo, lights from the "
               "chrome sphere, intensities from the grey sphere, nominal 100 dpi; its depth-discontinuity map "
               "(Raskar et al. 2004) feeds the discontinuity lines and shadows.",
        "owl": "psm-seitz *owl*, solved as the cat.",
        "coin": "flatbed-coin: four registered scans (0/90/180/270°) solved by the flatbed photometric stereo "
                "(§3.3.6) at 1/4 size under a *nominal* lamp model a = (0, 0.55, 0.55, 0) — the data set has no "
                "calibration, so the relief depth is only indicative.",
    }
    for name in rows:
        lines.append(f"* **{name}** — {about.get(name, '')}")
    for name, why in failed.items():
        lines.append(f"* **{name}** — not drawn: {why}")
    lines.append("")
    for key, recipe in recipes.items():
        what = recipe.description if key.startswith("recipe-") else STYLES[key].doc.splitlines()[0]
        lines += [f"## {key}", "", what,
                  "", f"![{key}: {', '.join(rows)}](gallery/{key}.png)", "",
                  "```toml", recipe_to_toml(recipe).rstrip(), "```", ""]
    path.write_text("\n".join(lines))


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    data_dir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[3] / "shared" / "data"
    out_dir = Path(sys.argv[2]) if len(sys.argv) > 2 else Path(__file__).resolve().parents[2] / "docs"
    print(make_gallery(data_dir, out_dir))
