"""Recipes: TOML descriptions of illustrations that combine styles, per segment if wanted (§7.3,
Fig. 7.15), and the renderer that draws them on the image's own pixel grid.

A recipe file::

    name = "relief"
    description = "exaggerated shading with ridge and valley lines"
    background = [1.0, 1.0, 1.0]     # display RGB outside the fragment
    bits = 8                         # 8 or 16 bits per channel on output

    [preprocess]                     # optional, applied once before the styles
    smooth_mm = 0.0                  # foreshortening-corrected Gaussian (§7.2.1)
    bilateral = { sigma_x = 3.0, sigma_c = 0.1, sigma_n = 0.2 }   # eq. 7.2

    [segmentation]                   # optional: colour+normal segments for per-segment styles
    scale = 200.0
    normal_weight = 1.0

    [[layer]]                        # layers are drawn in order
    style = "exaggerated"            # any name in STYLES; other keys are the style's parameters
    scales = 8

    [[layer]]
    style = "ridges_valleys"
    blend = "normal"                 # normal | multiply | screen | darken | lighten
    opacity = 0.8
    segments = [0]                   # only on segment 0 (segments are numbered by decreasing area)
    # exclude_segments = [0]         # or everywhere except these

Shading styles cover the fragment (alpha = mask); line and shadow styles are ink with
alpha = strength. Every style and parameter is listed by ``tessera render --list-styles``.
"""

from __future__ import annotations

import inspect
import logging
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from common.render import lines as _lines
from common.render import paint as _paint
from common.render import shading as _shading
from common.render import shadows as _shadows
from common.render._util import Layer, display_albedo, grey
from common.rgbn.image import RGBNImage

log = logging.getLogger(__name__)

#: Directory of the recipes shipped with Tessera (``configs/recipes/<name>.toml``).
RECIPE_DIR = Path(__file__).resolve().parents[2] / "configs" / "recipes"
BLENDS = ("normal", "multiply", "screen", "darken", "lighten")
_LAYER_KEYS = ("style", "blend", "opacity", "segments", "exclude_segments")


@dataclass(frozen=True)
class Style:
    """A drawable style: ``draw(image, **params) -> Layer``; ``needs`` the RGBN channels it uses."""

    name: str
    draw: Callable[..., Layer]
    needs: frozenset
    doc: str

    def parameters(self) -> dict:
        """Parameter name -> default value."""
        sig = inspect.signature(self.draw)
        return {p.name: p.default for p in list(sig.parameters.values())[1:] if p.name != "labels"}


# ---- style adapters: RGBNImage -> Layer (thin; the algorithms live in the style modules) ----------

def _cover(image: RGBNImage, rgb) -> Layer:
    rgb = np.asarray(rgb, np.float32)
    return Layer(rgb if rgb.ndim == 3 else grey(rgb), image.mask.astype(np.float32))


def _ink(strength, colour) -> Layer:
    s = np.asarray(strength, np.float32)
    return Layer(np.broadcast_to(np.asarray(colour, np.float32), s.shape + (3,)).copy(), s)


def _colour(image: RGBNImage, use_albedo: bool):
    return display_albedo(image.albedo) if use_albedo else None


def draw_albedo(image: RGBNImage) -> Layer:
    """The colour of the fragment (display-encoded albedo)."""
    return _cover(image, display_albedo(image.albedo))


def draw_lambertian(image: RGBNImage, light=(135.0, 45.0), ambient: float = 0.15, colour: bool = True) -> Layer:
    """Lambertian shading of the colour (or of grey) under any light (§7.3.1)."""
    return _cover(image, _shading.lambertian(image.normals, light, albedo=_colour(image, colour), ambient=ambient))


def draw_raking(image: RGBNImage, azimuth_deg: float = 135.0, elevation_deg: float = 12.0, ambient: float = 0.05,
                colour: bool = False) -> Layer:
    """Raking light: Lambertian shading from a low elevation; shows tool marks and impressions."""
    return _cover(image, _shading.lambertian(image.normals, (azimuth_deg, elevation_deg),
                                             albedo=_colour(image, colour), ambient=ambient))


def draw_toon(image: RGBNImage, light=(135.0, 45.0), levels: int = 3, softness: float = 0.02, dark: float = 0.4,
              n_colours: int = 6, seed: int = 0) -> Layer:
    """Toon shading with smooth steps on k-means-quantized colour (n_colours = 0: grey) (§7.3.2)."""
    colours = None
    if n_colours > 0:
        colours = _shading.quantize_colours(display_albedo(image.albedo), n_colours, mask=image.mask, seed=seed)
    return _cover(image, _shading.toon(image.normals, light, levels=levels, softness=softness, dark=dark,
                                       colours=colours))


def draw_gooch(image: RGBNImage, light=(135.0, 45.0), colour: bool = True, blue: float = 0.4, yellow: float = 0.4,
               alpha: float = 0.2, beta: float = 0.6) -> Layer:
    """Gooch warm/cool shading."""
    return _cover(image, _shading.gooch(image.normals, light, albedo=_colour(image, colour), blue=blue,
                                        yellow=yellow, alpha=alpha, beta=beta))


def draw_exaggerated(image: RGBNImage, light=(135.0, 45.0), scales: int = 8, sigma0_px: float = 1.0,
                     sigma_ratio: float = 2.0, contrast: float = 10.0, detail: float = 0.5,
                     base_weight: float = 0.3, colour: bool = False) -> Layer:
    """Exaggerated shading (Rusinkiewicz et al. 2006), optionally multiplied with the colour (§7.3.5)."""
    s = _shading.exaggerated_shading(image.normals, light, mask=image.mask, scales=scales, sigma0_px=sigma0_px,
                                     sigma_ratio=sigma_ratio, contrast=contrast, detail=detail,
                                     base_weight=base_weight)
    return _cover(image, display_albedo(image.albedo) * s[..., None] if colour else s)


def draw_mean_curvature(image: RGBNImage, sigma_mm: float = 0.05, radius_mm: float = -1.0) -> Layer:
    """Mean curvature shading: convex light, concave dark, flat 0.5; radius_mm < 0 = auto contrast (§7.3.6)."""
    return _cover(image, _shading.mean_curvature_shading(image.normals, image.dpi, mask=image.mask,
                                                         sigma_mm=sigma_mm,
                                                         radius_mm=None if radius_mm < 0 else radius_mm))


def draw_multiscale_mean_curvature(image: RGBNImage, scales: int = 5, sigma0_mm: float = 0.1,
                                   sigma_ratio: float = 2.0, gain: float = -1.0, detail: float = 0.0) -> Layer:
    """Multiscale mean curvature shading (eq. 7.8); gain < 0 = auto contrast."""
    return _cover(image, _shading.multiscale_mean_curvature_shading(
        image.normals, image.dpi, mask=image.mask, scales=scales, sigma0_mm=sigma0_mm, sigma_ratio=sigma_ratio,
        gain=None if gain < 0 else gain, detail=detail))


def draw_discontinuity_lines(image: RGBNImage, threshold_deg: float = 20.0, softness_deg: float = 10.0,
                             outline: bool = True, width_px: float = 1.5, flash_gain: float = 2.5,
                             colour=(0.0, 0.0, 0.0)) -> Layer:
    """Lines along normal and depth discontinuities (flash map if any) and the outline (§7.3.3)."""
    return _ink(_lines.discontinuity_lines(image.normals, mask=image.mask, discontinuity=image.discontinuity,
                                           threshold_deg=threshold_deg, softness_deg=softness_deg,
                                           outline=outline, width_px=width_px, flash_gain=flash_gain), colour)


def draw_suggestive_contours(image: RGBNImage, radius_px: float = 4.0, fraction: float = 0.2, depth: float = 0.02,
                             min_length_px: int = 12, sigma_px: float = 1.0, width_px: float = 1.0,
                             colour=(0.0, 0.0, 0.0)) -> Layer:
    """Image-space suggestive contours with length pruning (DeCarlo et al. 2003) (§7.3.4)."""
    return _ink(_lines.suggestive_contours(image.normals, mask=image.mask, radius_px=radius_px, fraction=fraction,
                                           depth=depth, min_length_px=min_length_px, sigma_px=sigma_px,
                                           width_px=width_px), colour)


def draw_suggestive_contours_object(image: RGBNImage, sigma_px: float = 3.0, threshold: float = 0.05,
                                    min_length_px: int = 20, width_px: float = 1.0,
                                    colour=(0.0, 0.0, 0.0)) -> Layer:
    """Object-space suggestive contours from curvature derivatives (§7.3.4)."""
    return _ink(_lines.suggestive_contours_object(image.normals, image.dpi, mask=image.mask, sigma_px=sigma_px,
                                                  threshold=threshold, min_length_px=min_length_px,
                                                  width_px=width_px), colour)


def draw_ridges_valleys(image: RGBNImage, sigma_px: float = 1.5, threshold: float = -1.0, percentile: float = 90.0,
                        min_length_px: int = 8, width_px: float = 1.0, ridge_colour=(0.55, 0.1, 0.05),
                        valley_colour=(0.0, 0.0, 0.0)) -> Layer:
    """Ridge (convex crest) and valley (trough) lines; threshold < 0 picks the percentile (§7.3.4)."""
    ridge, valley = _lines.ridges_valleys(image.normals, image.dpi, mask=image.mask, sigma_px=sigma_px,
                                          threshold=None if threshold < 0 else threshold, percentile=percentile,
                                          min_length_px=min_length_px, width_px=width_px)
    alpha = np.maximum(ridge, valley)
    rgb = np.where((valley >= ridge)[..., None], np.asarray(valley_colour, np.float32),
                   np.asarray(ridge_colour, np.float32)).astype(np.float32)
    return Layer(rgb, alpha)


def draw_discontinuity_shadows(image: RGBNImage, light=(135.0, 45.0), length_px: float = 12.0,
                               softness_px: float = 1.5, strength: float = 0.6, steep_nz: float = 0.5,
                               outline: bool = True) -> Layer:
    """Fast discontinuity shadows (eqs. 7.9-7.11): drawn over the shading, darkening it by ``1 - strength*S``."""
    d = _shadows.discontinuity_sources(image.normals, mask=image.mask, discontinuity=image.discontinuity,
                                       steep_nz=steep_nz, outline=outline)
    s = _shadows.discontinuity_shadows(d, light, length_px=length_px, softness_px=softness_px)
    return _ink(s * np.float32(strength), (0.0, 0.0, 0.0))


def draw_watercolour(image: RGBNImage, light=(135.0, 45.0), sigma_x: float = 4.0, sigma_c: float = 0.08,
                     sigma_n: float = 0.3, relief: float = 0.6, paper: float = 0.25, edge_darkening: float = 0.8,
                     seed: int = 0) -> Layer:
    """Watercolour: bilateral-flattened washes, relief density, paper texture, edge darkening (§7.3.8)."""
    from common.rgbn.bilateral import joint_bilateral

    washes, _ = joint_bilateral(image.albedo, image.normals, sigma_x=sigma_x, sigma_c=sigma_c,
                                sigma_n=sigma_n if image.normals is not None else np.inf, mask=image.mask)
    return _cover(image, _paint.watercolour(display_albedo(washes), image.normals, light, mask=image.mask,
                                            relief=relief, paper=paper, edge_darkening=edge_darkening, seed=seed))


def draw_segment_boundaries(image: RGBNImage, labels=None, width_px: float = 1.0, colour=(0.0, 0.0, 0.0)) -> Layer:
    """Lines between the recipe's colour+normal segments (needs a [segmentation] section)."""
    if labels is None:
        raise ValueError("style 'segment_boundaries' needs a [segmentation] section in the recipe")
    edge = np.zeros(labels.shape, bool)
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[1:] |= labels[1:] != labels[:-1]
    edge &= image.mask
    return _ink(_lines._thicken(edge.astype(np.float32), width_px), colour)


def draw_normals(image: RGBNImage) -> Layer:
    """The normal map as colour (OpenGL convention, (n + 1) / 2)."""
    return _cover(image, (image.normals + 1.0) * 0.5)


_N, _C = frozenset({"normal"}), frozenset({"colour"})
STYLES: dict[str, Style] = {s.name: s for s in (
    Style("albedo", draw_albedo, _C, draw_albedo.__doc__),
    Style("lambertian", draw_lambertian, _N, draw_lambertian.__doc__),
    Style("raking", draw_raking, _N, draw_raking.__doc__),
    Style("toon", draw_toon, _N, draw_toon.__doc__),
    Style("gooch", draw_gooch, _N, draw_gooch.__doc__),
    Style("exaggerated", draw_exaggerated, _N, draw_exaggerated.__doc__),
    Style("mean_curvature", draw_mean_curvature, _N, draw_mean_curvature.__doc__),
    Style("multiscale_mean_curvature", draw_multiscale_mean_curvature, _N, draw_multiscale_mean_curvature.__doc__),
    Style("discontinuity_lines", draw_discontinuity_lines, frozenset(), draw_discontinuity_lines.__doc__),
    Style("suggestive_contours", draw_suggestive_contours, _N, draw_suggestive_contours.__doc__),
    Style("suggestive_contours_object", draw_suggestive_contours_object, _N,
          draw_suggestive_contours_object.__doc__),
    Style("ridges_valleys", draw_ridges_valleys, _N, draw_ridges_valleys.__doc__),
    Style("discontinuity_shadows", draw_discontinuity_shadows, frozenset(), draw_discontinuity_shadows.__doc__),
    Style("watercolour", draw_watercolour, _C, draw_watercolour.__doc__),
    Style("segment_boundaries", draw_segment_boundaries, frozenset({"segments"}), draw_segment_boundaries.__doc__),
    Style("normals", draw_normals, _N, draw_normals.__doc__),
)}


# ---- recipes -------------------------------------------------------------------------------

@dataclass
class Recipe:
    """A parsed recipe (see the module docstring for the TOML form)."""

    name: str
    layers: list[dict]
    description: str = ""
    background: tuple = (1.0, 1.0, 1.0)
    bits: int = 8
    preprocess: dict = field(default_factory=dict)
    segmentation: dict | None = None
    source: str = ""

    def __post_init__(self):
        validate_recipe(self)


def validate_recipe(recipe: Recipe) -> None:
    """Raise ValueError naming the first bad entry of a recipe."""
    where = f"recipe {recipe.name!r}"
    if recipe.bits not in (8, 16):
        raise ValueError(f"{where}: bits must be 8 or 16, got {recipe.bits!r}")
    bg = np.asarray(recipe.background, dtype=float)
    if bg.shape != (3,) or not np.all((bg >= 0) & (bg <= 1)):
        raise ValueError(f"{where}: background must be three numbers in [0, 1], got {recipe.background!r}")
    if not recipe.layers:
        raise ValueError(f"{where}: needs at least one [[layer]]")
    unknown = set(recipe.preprocess) - {"smooth_mm", "bilateral"}
    if unknown:
        raise ValueError(f"{where}: unknown [preprocess] key(s) {sorted(unknown)}; known: smooth_mm, bilateral")
    if recipe.segmentation is not None:
        from common.rgbn.segmentation import segment_rgbn

        known = set(inspect.signature(segment_rgbn).parameters) - {"albedo", "normals", "mask"}
        bad = set(recipe.segmentation) - known
        if bad:
            raise ValueError(f"{where}: unknown [segmentation] key(s) {sorted(bad)}; known: {sorted(known)}")
    for i, layer in enumerate(recipe.layers):
        lw = f"{where}, layer {i + 1}"
        if not isinstance(layer, dict) or "style" not in layer:
            raise ValueError(f"{lw}: every [[layer]] needs a 'style'")
        style = STYLES.get(layer["style"])
        if style is None:
            raise ValueError(f"{lw}: unknown style {layer['style']!r}; known: {', '.join(sorted(STYLES))}")
        if layer.get("blend", "normal") not in BLENDS:
            raise ValueError(f"{lw}: blend must be one of {BLENDS}, got {layer.get('blend')!r}")
        opacity = layer.get("opacity", 1.0)
        if not isinstance(opacity, (int, float)) or not 0 <= opacity <= 1:
            raise ValueError(f"{lw}: opacity must be a number in [0, 1], got {opacity!r}")
        if ("segments" in layer or "exclude_segments" in layer or "segments" in style.needs) \
                and recipe.segmentation is None:
            raise ValueError(f"{lw}: per-segment drawing needs a [segmentation] section")
        params = set(layer) - set(_LAYER_KEYS)
        bad = params - set(style.parameters())
        if bad:
            raise ValueError(f"{lw}: style {style.name!r} has no parameter(s) {sorted(bad)}; "
                             f"it takes {', '.join(style.parameters()) or 'none'}")


def parse_recipe(text: str, *, name: str = "recipe") -> Recipe:
    """A :class:`Recipe` from TOML text."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"recipe {name!r} is not valid TOML: {exc}") from exc
    known = {"name", "description", "background", "bits", "preprocess", "segmentation", "layer"}
    bad = set(doc) - known
    if bad:
        raise ValueError(f"recipe {name!r}: unknown top-level key(s) {sorted(bad)}; known: {sorted(known)}")
    return Recipe(name=doc.get("name", name), description=doc.get("description", ""),
                  background=tuple(doc.get("background", (1.0, 1.0, 1.0))), bits=doc.get("bits", 8),
                  preprocess=dict(doc.get("preprocess", {})), segmentation=doc.get("segmentation"),
                  layers=[dict(layer) for layer in doc.get("layer", [])], source=text)


def load_recipe(path_or_name: str | Path) -> Recipe:
    """Load a recipe file, or a shipped recipe by name (``configs/recipes/<name>.toml``)."""
    p = Path(path_or_name)
    if not p.is_file():
        shipped = RECIPE_DIR / f"{path_or_name}.toml"
        if not shipped.is_file():
            names = sorted(q.stem for q in RECIPE_DIR.glob("*.toml"))
            raise FileNotFoundError(f"recipe {path_or_name!r} is neither a file nor a shipped recipe "
                                    f"(shipped: {', '.join(names)})")
        p = shipped
    return parse_recipe(p.read_text(), name=p.stem)


def recipe_to_toml(recipe: Recipe) -> str:
    """TOML text of a recipe (the form :func:`parse_recipe` reads)."""

    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(float(v)) if isinstance(v, float) else str(v)
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {value(x)}" for k, x in v.items()) + " }"
        raise ValueError(f"cannot write {v!r} as TOML")

    out = [f"name = {value(recipe.name)}"]
    if recipe.description:
        out.append(f"description = {value(recipe.description)}")
    out.append(f"background = {value(list(recipe.background))}")
    out.append(f"bits = {recipe.bits}")
    if recipe.preprocess:
        out += ["", "[preprocess]"] + [f"{k} = {value(v)}" for k, v in recipe.preprocess.items()]
    if recipe.segmentation is not None:
        out += ["", "[segmentation]"] + [f"{k} = {value(v)}" for k, v in recipe.segmentation.items()]
    for layer in recipe.layers:
        out += ["", "[[layer]]"] + [f"{k} = {value(v)}" for k, v in layer.items()]
    return "\n".join(out) + "\n"


def style_recipe(style: str, **params) -> Recipe:
    """A one-layer recipe drawing ``style`` (with its parameters); line and shadow styles are
    drawn over the fragment's colour so they have something to sit on."""
    if style not in STYLES:
        raise ValueError(f"unknown style {style!r}; known: {', '.join(sorted(STYLES))}")
    layers = [dict(style=style, **params)]
    if style in ("discontinuity_lines", "suggestive_contours", "suggestive_contours_object", "ridges_valleys",
                 "discontinuity_shadows"):
        layers.insert(0, {"style": "albedo"})
    recipe = Recipe(name=style, layers=layers)
    recipe.source = recipe_to_toml(recipe)
    return recipe


@dataclass
class Rendering:
    """A drawn illustration: display RGB in [0, 1] and coverage, on the input's pixel grid."""

    rgb: np.ndarray
    alpha: np.ndarray
    recipe: Recipe
    skipped: list = field(default_factory=list)


def render(image: RGBNImage, recipe: Recipe | str, *, progress: Callable[[float, str], None] | None = None) -> Rendering:
    """Draw ``image`` with a recipe (or a recipe name / file / style name).

    Layers whose style needs normals are skipped (and listed in ``Rendering.skipped``) for a
    colour-only image; if none remains the albedo is drawn.

    References
    ----------
    Toler-Franklin 2011, §7.3 and Fig. 7.15 (per-segment styles).
    """
    if isinstance(recipe, str):
        recipe = style_recipe(recipe) if recipe in STYLES else load_recipe(recipe)
    if not isinstance(image, RGBNImage):
        raise ValueError(f"image must be an RGBNImage, got {type(image).__name__}")
    image = _preprocess(image, recipe.preprocess)
    layers = recipe.layers
    skipped = [layer["style"] for layer in layers if "normal" in STYLES[layer["style"]].needs and image.normals is None]
    if skipped:
        log.warning("image has no normals: skipping %s", ", ".join(skipped))
        layers = [layer for layer in layers if layer["style"] not in skipped] or [{"style": "albedo"}]
    labels = None
    if any("segments" in layer or "exclude_segments" in layer or "segments" in STYLES[layer["style"]].needs
           for layer in layers):
        from common.rgbn.segmentation import segment_rgbn

        labels = segment_rgbn(image.albedo, image.normals, mask=image.mask, **(recipe.segmentation or {}))
    canvas = np.empty(image.shape + (3,), np.float32)
    canvas[:] = np.asarray(recipe.background, np.float32)
    cover = np.zeros(image.shape, np.float32)
    for i, layer in enumerate(layers):
        if progress:
            progress(i / len(layers), f"drawing {layer['style']}")
        style = STYLES[layer["style"]]
        params = {k: (tuple(v) if isinstance(v, list) else v) for k, v in layer.items() if k not in _LAYER_KEYS}
        if "segments" in style.needs:
            params["labels"] = labels
        drawn = style.draw(image, **params)
        a = drawn.alpha * np.float32(layer.get("opacity", 1.0))
        if labels is not None and "segments" in layer:
            a = a * np.isin(labels, layer["segments"])
        if labels is not None and "exclude_segments" in layer:
            a = a * ~np.isin(labels, layer["exclude_segments"])
        canvas = _blend(canvas, drawn.rgb, a.astype(np.float32), layer.get("blend", "normal"))
        np.maximum(cover, a, out=cover)
    if progress:
        progress(1.0, "done")
    return Rendering(np.clip(canvas, 0.0, 1.0), np.clip(np.maximum(cover, image.mask), 0.0, 1.0), recipe, skipped)


def _preprocess(image: RGBNImage, pre: dict) -> RGBNImage:
    if not pre:
        return image
    if pre.get("smooth_mm", 0) > 0:
        from common.rgbn.smoothing import smooth_rgbn

        image = smooth_rgbn(image, float(pre["smooth_mm"]))
    if pre.get("bilateral"):
        from common.rgbn.bilateral import joint_bilateral

        opts = dict(pre["bilateral"])
        albedo, normals = joint_bilateral(image.albedo, image.normals, mask=image.mask, **opts)
        image = replace(image, albedo=albedo, normals=normals if normals is not None else image.normals)
    return image


def _blend(base: np.ndarray, rgb: np.ndarray, alpha: np.ndarray, mode: str) -> np.ndarray:
    a = alpha[..., None]
    if mode == "normal":
        top = rgb
    elif mode == "multiply":
        top = base * rgb
    elif mode == "screen":
        top = 1.0 - (1.0 - base) * (1.0 - rgb)
    elif mode == "darken":
        top = np.minimum(base, rgb)
    elif mode == "lighten":
        top = np.maximum(base, rgb)
    else:
        raise ValueError(f"blend must be one of {BLENDS}, got {mode!r}")
    return base + (top - base) * a
