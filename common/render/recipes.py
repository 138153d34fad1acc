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

import cv2
import numpy as np

from common.render import lines as _lines
from common.render import paint as _paint
from common.render import shading as _shading
from common.render import enhance as _enhance
from common.render import shadows as _shadows
from common.render._util import Layer, as_light, display_albedo, dot_light, grey
from common.rgbn.image import RGBNImage

log = logging.getLogger(__name__)

#: Directory of the recipes shipped with Tessera (``configs/recipes/<name>.toml``).
RECIPE_DIR = Path(__file__).resolve().parents[2] / "configs" / "recipes"
BLENDS = ("normal", "multiply", "screen", "darken", "lighten", "overlay", "soft_light", "lightness")
_LAYER_KEYS = ("style", "blend", "opacity", "segments", "exclude_segments")


@dataclass(frozen=True)
class Style:
    """A drawable style: ``draw(image, **params) -> Layer``; ``needs`` the RGBN channels it uses."""

    name: str
    draw: Callable[..., Layer]
    needs: frozenset
    doc: str

    @property
    def summary(self) -> str:
        """The first paragraph of ``doc`` on one line (its first line alone may stop mid-sentence)."""
        return " ".join(self.doc.strip().split("\n\n")[0].split())

    def parameters(self) -> dict:
        """Parameter name -> default value."""
        sig = inspect.signature(self.draw)
        return {p.name: p.default for p in list(sig.parameters.values())[1:] if p.name != "labels"}


# ---- style adapters: RGBNImage -> Layer (thin; the algorithms live in the style modules) ----------
#
# Parameters whose default is "auto" are chosen from the data (robust percentiles, the noise of
# the normal map, the dpi); the value chosen is returned in Layer.resolved, so that drawing again
# with it (another tile of the same image) gives the same tones.

AUTO = "auto"
_cache: dict = {}


def _is_auto(value) -> bool:
    return isinstance(value, str) and value == AUTO


def _is_none(value) -> bool:
    return isinstance(value, str) and value == "none"


def _whole(image: RGBNImage) -> RGBNImage:
    """The image whose statistics the "auto" values of ``image`` are taken from: ``image``
    itself, or, for a window of the image being drawn (:func:`_draw_where_shown`), that image —
    so a layer drawn window by window picks the values a drawing of the whole image picks."""
    window = _cache.get("window")
    return window[0] if window is not None and image is window[1] else image


def _cover(image: RGBNImage, rgb, resolved=None) -> Layer:
    rgb = np.asarray(rgb, np.float32)
    return Layer(rgb if rgb.ndim == 3 else grey(rgb), image.mask.astype(np.float32), resolved or {})


def _ink(strength, colour, resolved=None) -> Layer:
    s = np.asarray(strength, np.float32)
    return Layer(np.broadcast_to(np.asarray(colour, np.float32), s.shape + (3,)).copy(), s, resolved or {})


def _colour(image: RGBNImage, use_albedo: bool):
    return display_albedo(image.albedo) if use_albedo else None


def _noise_px(image: RGBNImage, value, resolved: dict, key: str, *, factor: float = 1.0, floor: float = 0.0) -> float:
    """A smoothing scale in pixels: ``value``, or for "auto" ``factor`` x the scale that brings the
    normal map's noise down (:func:`common.render.enhance.relief_scale_px`), at least ``floor``.
    The noise is measured on the centred calibration window (:func:`common.render.tiles.calibration_window`,
    the tiled renderer's; the whole image when it is smaller or the window holds under a tenth of
    the fragment): a statistic of the pixels, which a few megapixels of them give as well as all."""
    from common.render.tiles import calibration_window

    image = _whole(image)
    if _is_auto(value) and image.normals is None:
        value = 0.0
    if _is_auto(value):
        k = (id(image.normals), image.shape)
        if k not in _cache:
            r0, r1, c0, c1 = calibration_window(image.shape)
            window = (slice(r0, r1), slice(c0, c1))
            if np.count_nonzero(image.mask[window]) * 10 < np.count_nonzero(image.mask):
                window = (slice(None), slice(None))
            _cache[k] = _enhance.relief_scale_px(image.normals[window], image.dpi, image.mask[window])
            log.info("noise of the normal map: %s -> smoothing %.2f px", _cache[k][1], _cache[k][0])
        value = max(factor * _cache[k][0], floor)
    resolved[key] = round(float(value), 4)
    return float(value)


def _range(values, mask, value, resolved: dict, key: str, clip_percent: float = 0.5) -> tuple[float, float]:
    """``[low, high]`` of a robust stretch: ``value`` or, for "auto", the ``clip_percent`` and
    ``100 - clip_percent`` percentiles."""
    lo, hi = (_enhance.robust_range(values, mask, clip_percent=clip_percent) if _is_auto(value)
              else (float(value[0]), float(value[1])))
    resolved[key] = [lo, hi]
    return lo, hi


def _zero_scale(values, mask, value, resolved: dict, key: str, clip_percent: float = 5.0) -> float:
    """Scale of a zero-centred signal: ``value`` or, for "auto", the ``100 - clip_percent``
    percentile of |values| (the tone curve puts it at 0.2 / 0.8)."""
    ref = _enhance.symmetric_scale(values, mask, clip_percent=clip_percent) if _is_auto(value) else float(value)
    resolved[key] = ref
    return ref


def _exposed_colour(image: RGBNImage, value, resolved: dict, key: str = "exposure", *,
                    albedo: np.ndarray | None = None) -> np.ndarray:
    """Display colour of the fragment with its lightness exposed (:func:`_lightness_exposure`);
    ``albedo``: the colours to expose so (some pixels of the image's), None for the image's."""
    rng = _lightness_exposure(image, value, resolved, key)
    albedo = image.albedo if albedo is None else albedo
    if rng is None:
        return display_albedo(albedo)
    return _enhance.lightness_relief(albedo, None, strength=0.0, exposure=rng)


def _lightness_exposure(image: RGBNImage, value, resolved: dict, key: str = "exposure"):
    """CIELAB L* of the colour: the 5th / 95th percentiles drawn at L* 20 / 80 ("auto"), a given
    [low, high], or as captured ("none")."""
    if _is_none(value):
        resolved[key] = "none"
        return None
    whole = _whole(image)
    rng = _enhance.lightness_range(whole.albedo, whole.mask) if _is_auto(value) else (float(value[0]), float(value[1]))
    resolved[key] = [float(rng[0]), float(rng[1])]
    return rng


def _smoothed(image: RGBNImage, sigma_px: float) -> np.ndarray:
    """The normals smoothed at ``sigma_px`` (:func:`common.rgbn.smoothing.smooth_normals`). In a
    recipe of several layers each scale is computed once and shared (exaggerated shading's finest
    level is the noise scale that discontinuity lines and the lit styles smooth at); a single
    layer keeps nothing, so its memory is not raised."""
    from common.rgbn.smoothing import smooth_normals

    if not sigma_px > 0:
        return image.normals
    k = ("smoothed", id(image.normals), image.shape, float(sigma_px))
    if k in _cache:
        return _cache[k]
    out = smooth_normals(image.normals, sigma_px, mask=image.mask)
    if _cache.get("share_smoothed"):
        _cache[k] = out
    return out


def _level_sigma(image: RGBNImage, level, resolved: dict) -> float:
    """Scale (px) of the undulation that levelling removes, 0 for none: ``level`` is "auto",
    true/false or a number. "auto" levels a near-flat surface — its coarse normals all point
    nearly one way (length of their mean > 0.95: a painting, a relief, even when near lights
    tilted the whole solve) — and leaves a curved object (a ball: about 0.7) alone."""
    image = _whole(image)   # a window is levelled as the whole image is
    sigma = _enhance.levelling_sigma_px(image.shape)
    if _is_auto(level):
        flat = image.mask.any() and _enhance.near_flat_facing(_coarse(image, sigma).values) is not None
        level = sigma if flat else 0.0
    elif isinstance(level, bool):
        level = sigma if level else 0.0
    resolved["level"] = float(level)
    return float(level)


def _coarse(image: RGBNImage, sigma: float) -> np.ndarray:
    """The coarse normal field levelling smooths at ``sigma`` (a :class:`enhance.Coarse`): a
    tile's window of the whole image's when the tiles were given it (:func:`_render_whole`'s
    ``coarse``), else computed from this image; for a window of the image being drawn
    (:func:`_draw_where_shown`), the window of the image's field."""
    whole = _whole(image)
    if whole is not image:
        r0, c0 = _cache["window"][2]
        return _enhance.coarse_window(_coarse(whole, sigma), r0, r0 + image.shape[0], c0, c0 + image.shape[1])
    seeded = _cache.get(("whole coarse", float(sigma)))
    if seeded is not None:
        return seeded
    k = ("coarse", id(image.normals), image.shape, sigma)
    if k not in _cache:
        _cache[k] = _enhance.coarse_normals(image.normals, sigma, mask=image.mask, full_size=False,
                                            origin=image.attrs.get("tile_origin", (0, 0)))
    return _cache[k]


def _cosines(image: RGBNImage, sigma_px: float, light, level, resolved: dict, *, half: bool = False):
    """``(n . l, n . h or None)``, (H, W) float32: the cosines of the normals smoothed at
    ``sigma_px`` with the light — for a levelled surface the per-pixel light that rakes it relative
    to its own slow undulation (:func:`common.render.enhance.level_light`) — and, with ``half``,
    with the half vector of the light and the view (:func:`common.render.enhance.half_vector`).

    :func:`common.rgbn.smoothing.smoothed_cosines` computes them a strip of rows at a time, so the
    lit styles' only full-size arrays are these planes; in a recipe that shares its smoothed
    normals between layers (:func:`_smoothed`) they are taken from those."""
    from common.rgbn.smoothing import smoothed_cosines, unit_rows

    sigma = _level_sigma(image, level, resolved)
    field = _enhance.levelled_light(light, _coarse(image, sigma)) if sigma > 0 else None
    l = as_light(light)
    lz = None   # a per-pixel light's z, kept for its half vector
    if field is None:
        directions = [l, _enhance.half_vector(l)]
    else:
        lz = np.empty(image.shape, np.float32) if half else None

        def light_rows(r0, r1):
            rows = unit_rows(field.full(image.shape, rows=(r0, r1)))
            if lz is not None:
                lz[r0:r1] = rows[..., 2]
            return rows

        # with h = (l + v) / |l + v|, v the view (0, 0, 1): n . h = (n . l + n . v) / sqrt(2 + 2 l_z),
        # so the half vector's cosine comes from the view's, not from a field of half vectors
        directions = [light_rows, np.array([0.0, 0.0, 1.0], np.float32)]
    directions = directions[:2 if half else 1]
    if _cache.get("share_smoothed") and sigma_px > 0:
        cosines = smoothed_cosines(_smoothed(image, sigma_px), 0.0, directions, mask=image.mask)
    else:
        cosines = smoothed_cosines(image.normals, float(sigma_px), directions, mask=image.mask)
    if not half:
        return cosines[0], None
    cos_nh = cosines[1]
    if lz is not None:
        cos_nh += cosines[0]
        lz *= np.float32(2.0)
        lz += np.float32(2.0)
        np.maximum(lz, np.float32(1e-24), out=lz)   # |l + v|^2; l = -v has no half vector: 0, as half_vector
        np.sqrt(lz, out=lz)
        cos_nh /= lz
    return cosines[0], cos_nh


def _levelled(image: RGBNImage, level, resolved: dict) -> np.ndarray:
    """The normals levelled (:func:`common.render.enhance.level_normals`) when ``level`` says so."""
    sigma = _level_sigma(image, level, resolved)
    return (_enhance.level_normals(image.normals, sigma, mask=image.mask,
                                   origin=image.attrs.get("tile_origin", (0, 0)),
                                   coarse=_cache.get(("whole coarse", float(sigma))))
            if sigma > 0 else image.normals)


def draw_albedo(image: RGBNImage, exposure="auto") -> Layer:
    """The colour of the fragment; exposure stretches CIELAB lightness only ("none" = as captured)."""
    r = {}
    return _cover(image, _exposed_colour(image, exposure, r), r)


def _lit(image, light, ambient, colour, exposure, sigma_px, level, colour_exposure) -> Layer:
    r = {}
    cosine, _ = _cosines(image, _noise_px(image, sigma_px, r, "sigma_px"), light, level, r)
    shade = _shading.lambertian_of_cosine(cosine, ambient=ambient)
    del cosine
    if colour:
        # the exposed colour, lit: relief on the lightness, the shade's median = the colour as is
        # ("none": the shade as computed, 0.5 = the colour as is)
        if _is_none(exposure):
            r["exposure"] = "none"
            relief = 2.0 * shade - 1.0
        else:
            lo, hi = _range(shade, image.mask, exposure, r, "exposure", clip_percent=5.0)
            relief = 2.0 * _enhance.tone_curve(shade, lo, hi) - 1.0
        rng = _lightness_exposure(image, colour_exposure, r, "colour_exposure")
        return _cover(image, _enhance.lightness_relief(image.albedo, relief, strength=0.8, exposure=rng), r)
    if _is_none(exposure):
        r["exposure"] = "none"
        return _cover(image, shade, r)
    lo, hi = _range(shade, image.mask, exposure, r, "exposure", clip_percent=5.0)
    return _cover(image, _enhance.tone_curve(shade, lo, hi), r)


def draw_lambertian(image: RGBNImage, light=(135.0, 45.0), ambient: float = 0.15, colour: bool = True,
                    exposure="auto", sigma_px="auto", level="auto", colour_exposure="auto") -> Layer:
    """Lambertian shading of the colour (or of grey) under any light, exposed from robust percentiles;
    with colour it is drawn on the colour's lightness (§7.3.1)."""
    return _lit(image, light, ambient, colour, exposure, sigma_px, level, colour_exposure)


def draw_raking(image: RGBNImage, azimuth_deg: float = 135.0, elevation_deg: float = 12.0, ambient: float = 0.05,
                colour: bool = False, exposure="auto", sigma_px="auto", level="auto",
                colour_exposure="auto") -> Layer:
    """Raking light: Lambertian shading from a low elevation (relative to a near-flat surface's own
    plane, level), exposed from robust percentiles."""
    return _lit(image, (azimuth_deg, elevation_deg), ambient, colour, exposure, sigma_px, level, colour_exposure)


def draw_toon(image: RGBNImage, light=(135.0, 45.0), levels: int = 3, softness: float = 0.05, dark: float = 0.55,
              n_colours: int = 6, seed: int = 0, sigma_px="auto", palette="auto", level="auto",
              colour_exposure="auto") -> Layer:
    """Toon shading with smooth steps on k-means-quantized colour (n_colours = 0: grey) (§7.3.2).

    The normals are smoothed at 3x the noise scale first, so bands follow the shape, not noise."""
    r = {}
    cosine, _ = _cosines(image, _noise_px(image, sigma_px, r, "sigma_px", factor=3.0), light, level, r)
    colours = None
    if n_colours > 0:
        shown = _exposed_colour(image, colour_exposure, r, "colour_exposure")
        if _is_auto(palette):
            whole = _whole(image)
            if whole is image:
                centres = _shading.kmeans_palette(shown, n_colours, mask=image.mask, seed=seed)
            else:   # a window: the whole image's palette, fitted on its pixels' colours only
                at = _shading.palette_pixels(whole.mask, seed=seed)
                sample = _exposed_colour(image, r["colour_exposure"], {}, albedo=whole.albedo.reshape(-1, 3)[at][None])
                centres = _shading.kmeans_palette(sample, n_colours, seed=seed)
        else:
            centres = np.asarray(palette, np.float32).reshape(-1, 3)
        r["palette"] = centres.round(6).tolist()
        colours = _shading.nearest_colours(shown, centres, mask=image.mask)
    return _cover(image, _shading.toon_of_cosine(cosine, levels=levels, softness=softness, dark=dark,
                                                 colours=colours), r)


def draw_gooch(image: RGBNImage, light=(135.0, 45.0), colour: bool = True, blue: float = 0.15,
               yellow: float = 0.15, alpha: float = 0.5, beta: float = 0.8, sigma_px="auto", level="auto",
               colour_exposure="auto", exposure="auto") -> Layer:
    """Gooch warm/cool shading (technical illustration of shape: its hues are not the object's)."""
    r = {}
    cosine, _ = _cosines(image, _noise_px(image, sigma_px, r, "sigma_px", factor=2.0), light, level, r)
    kd = _exposed_colour(image, colour_exposure, r, "colour_exposure") if colour else None
    out = _shading.gooch_of_cosine(cosine, albedo=kd, blue=blue, yellow=yellow, alpha=alpha, beta=beta)
    del cosine, kd
    # Gooch compresses lightness into its warm-cool ramp: expose the result's lightness (hues kept)
    return _cover(image, _exposed_lightness(out, image.mask, exposure, r, "exposure", only_narrow=False), r)


def _exaggerated_signal(image, light, scales, sigma0_px, sigma_ratio, contrast, detail, base_weight, r):
    s0 = _noise_px(image, sigma0_px, r, "sigma0_px")
    shared = _smoothed(image, s0) if _cache.get("share_smoothed") and s0 > 0 else None
    d = _shading.exaggerated_shading(image.normals, light, mask=image.mask, scales=scales, sigma0_px=s0,
                                     sigma_ratio=sigma_ratio, contrast=contrast, detail=detail,
                                     base_weight=base_weight, finest=shared,
                                     origin=image.attrs.get("tile_origin", (0, 0)))
    d -= np.float32(0.5)
    return d


def draw_exaggerated(image: RGBNImage, light=(135.0, 45.0), scales: int = 6, sigma0_px="auto",
                     sigma_ratio: float = 2.0, contrast: float = 10.0, detail: float = 0.5,
                     base_weight: float = 0.3, colour: bool = False, tones="auto", strength: float = 0.7,
                     exposure="auto") -> Layer:
    """Exaggerated shading (Rusinkiewicz et al. 2006) stretched to the tone range; with colour = true
    it is drawn on the colour's lightness only (hue and chroma kept) (§7.3.5)."""
    r = {}
    d = _exaggerated_signal(image, light, scales, sigma0_px, sigma_ratio, contrast, detail, base_weight, r)
    lo, hi = _range(d, image.mask, tones, r, "tones", clip_percent=5.0)
    tone = _enhance.tone_curve(d, lo, hi)
    if colour:
        rng = _lightness_exposure(image, exposure, r)
        return _cover(image, _enhance.lightness_relief(image.albedo, 2.0 * tone - 1.0, strength=strength,
                                                       exposure=rng), r)
    return _cover(image, tone, r)


def draw_colour_relief(image: RGBNImage, light=(135.0, 35.0), sigma_mm: float = 1.0, fine_px="auto",
                       strength="auto", detail_scale="auto", exposure="auto") -> Layer:
    """Colour plus relief: normal unsharp masking on the colour's lightness only (hue kept).

    The detail shading (:func:`common.render.enhance.detail_shading`) is drawn on CIELAB L* of the
    exposed colour, so the paint keeps its hue and chroma; the default illustration of a painted
    surface."""
    r = {}
    fine = _noise_px(image, fine_px, r, "fine_px")
    sigma = max(float(sigma_mm) * image.dpi / 25.4, 2.0 * fine + 1.0)
    d = _enhance.detail_shading(image.normals, light, mask=image.mask, sigma_px=sigma, fine_px=fine)
    s = _zero_scale(d, image.mask, detail_scale, r, "detail_scale")
    rng = _lightness_exposure(image, exposure, r)
    if _is_auto(strength):
        # a uniform material (one metal, one plaster: its lightness varies < 30 L*) has only its
        # relief to show and gets more room for it: 0.6 for a painting, up to 0.95
        spread = _enhance.lightness_spread(image.albedo, image.mask)
        strength = float(np.clip(0.6 + (30.0 - spread) / 60.0, 0.6, 0.95))
    r["strength"] = float(strength)
    relief = 2.0 * _enhance.tone_curve(d, -s, s) - 1.0
    return _cover(image, _enhance.lightness_relief(image.albedo, relief, strength=strength, exposure=rng), r)


def draw_normal_unsharp(image: RGBNImage, light=(135.0, 45.0), sigma_mm: float = 1.0, gain: float = 3.0,
                        colour: bool = True, exposure="auto") -> Layer:
    """RTIViewer's normal unsharp masking: detail of the normals amplified, relit, times the colour."""
    r = {}
    sigma = max(float(sigma_mm) * image.dpi / 25.4, 1.0)
    shade = _enhance.normal_unsharp_masking(image.normals, light, mask=image.mask, sigma_px=sigma, gain=gain)
    if _is_none(exposure):   # RTIViewer's picture as computed
        r["exposure"] = "none"
        return _cover(image, np.clip(display_albedo(image.albedo) * shade[..., None] if colour else shade, 0.0, 1.0), r)
    if not colour:
        lo, hi = _range(shade, image.mask, exposure, r, "exposure", clip_percent=5.0)
        return _cover(image, _enhance.tone_curve(shade, lo, hi), r)
    # RTIViewer's picture (colour x shading), then exposed on its lightness (hue kept)
    from common.rgbn.io import srgb_to_linear

    lit = srgb_to_linear(display_albedo(image.albedo) * shade[..., None])
    rng = (_enhance.lightness_range(lit, image.mask) if _is_auto(exposure)
           else (float(exposure[0]), float(exposure[1])))
    r["exposure"] = [float(rng[0]), float(rng[1])]
    return _cover(image, _enhance.lightness_relief(lit, None, strength=0.0,
                                                   exposure=rng), r)


def draw_specular(image: RGBNImage, light=(135.0, 45.0), kd: float = 0.6, ks: float = 0.6, exponent: float = 30.0,
                  colour: bool = True, sigma_px="auto", exposure="auto", level="auto",
                  colour_exposure="auto", lightness="auto") -> Layer:
    """Specular enhancement (Malzbender et al. 2001): the surface drawn as glossy, highlights show
    slope; the brightest highlights roll off below white (exposure), then a picture whose lightness
    is narrow is spread over the tone range (lightness: hue kept)."""
    r = {}
    cos_nl, cos_nh = _cosines(image, _noise_px(image, sigma_px, r, "sigma_px"), light, level, r, half=True)
    base = _exposed_colour(image, colour_exposure, r, "colour_exposure") if colour else None
    out = _enhance.specular_of_cosines(cos_nl, cos_nh, albedo=base, kd=kd, ks=ks, exponent=exponent, clip=False)
    del cos_nl, cos_nh, base
    if _is_none(exposure):   # as computed: no scaling by the brightest, no roll-off
        r["exposure"] = "none"
        np.clip(out, 0.0, 1.0, out=out)
    else:
        lum = out @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        lo, hi = _range(lum, image.mask, exposure, r, "exposure")
        del lum
        out *= np.float32(1.0 / max(hi, 1e-6))
        _enhance.shoulder(out, out=out)
    # diffuse times an exposed colour plus highlights scaled by the brightest: the lightness a
    # uniform material keeps can be narrow (a coin: 47 % of the tone range), so it is exposed too
    return _cover(image, _exposed_lightness(out, image.mask, lightness, r), r)


#: "auto" lightness leaves a drawn picture whose CIELAB lightness spans at least this much (L*)
#: between its 5th and 95th percentiles as drawn: a little over half the tone range, as the
#: luminance of display values spans a few per cent less than L* does (the flatbed coin's
#: watercolour: 50.7 L*, 49.9 % of the range).
KEEP_LIGHTNESS_SPAN = 55.0


def _exposed_lightness(display: np.ndarray, mask, value, resolved: dict, key: str = "lightness", *,
                       only_narrow: bool = True) -> np.ndarray:
    """A drawn colour picture (display values in [0, 1]) with its CIELAB lightness exposed: the
    5th / 95th percentiles drawn at L* 20 / 80 ("auto", :func:`common.render.enhance.lightness_range`;
    with ``only_narrow`` only when they are less than :data:`KEEP_LIGHTNESS_SPAN` apart, judged on
    a sample, else "none"), a given [low, high] in L*, or as drawn ("none"); hue and chroma kept."""
    from common.rgbn.io import srgb_to_linear

    if _is_auto(value) and only_narrow:
        sample = srgb_to_linear(_enhance.masked_stride(display, mask))
        lightness = cv2.cvtColor(np.ascontiguousarray(sample[None]), cv2.COLOR_LRGB2Lab)[0, :, 0]
        lo, hi = _enhance.robust_range(lightness, clip_percent=5.0)
        if hi - lo >= KEEP_LIGHTNESS_SPAN:
            value = "none"
    if isinstance(value, str) and value == "none":
        resolved[key] = "none"
        return display
    # the picture decoded only where measured and a strip at a time as it is exposed
    rng = (_enhance.lightness_range(display, mask, encoded=True) if _is_auto(value)
           else (float(value[0]), float(value[1])))
    resolved[key] = [float(rng[0]), float(rng[1])]
    return _enhance.lightness_relief(display, None, strength=0.0, exposure=rng, encoded=True)


def draw_mean_curvature(image: RGBNImage, sigma_mm="auto", radius_mm="auto") -> Layer:
    """Mean curvature shading: convex light, concave dark, flat 0.5; radius_mm = the radius drawn at
    0.8 / 0.2, "auto" = the 90th percentile of |H| (§7.3.6)."""
    from common.rgbn.curvature import mean_curvature

    r = {}
    if _is_auto(sigma_mm):
        sigma_px = _noise_px(image, AUTO, {}, "sigma_px", factor=2.0)
        sigma_mm = sigma_px * 25.4 / image.dpi
    r["sigma_mm"] = float(sigma_mm)
    H = mean_curvature(image.normals, image.dpi, mask=image.mask, sigma_px=float(sigma_mm) * image.dpi / 25.4)
    if isinstance(radius_mm, (int, float)) and radius_mm < 0:
        radius_mm = AUTO
    # radius_mm: the radius of curvature drawn at 0.8 (convex) / 0.2 (concave)
    # the 90th percentile of |H| is about the 95th of H for convex and concave alike
    scale = _zero_scale(H, image.mask, AUTO if _is_auto(radius_mm) else 1.0 / float(radius_mm), r, "_scale",
                        clip_percent=10.0)
    r["radius_mm"] = 1.0 / scale
    r.pop("_scale")
    return _cover(image, _enhance.tone_curve(H, -scale, scale), r)


def draw_multiscale_mean_curvature(image: RGBNImage, scales: int = 5, sigma0_mm="auto",
                                   sigma_ratio: float = 2.0, gain="auto", detail: float = 0.0) -> Layer:
    """Multiscale mean curvature shading (eq. 7.8); "auto" gain draws the 5th / 95th percentiles of the sum
    at 0.2 / 0.8; a number g draws 0 (flat) at 0.5 and 1/g at 0.8."""
    r = {}
    if _is_auto(sigma0_mm):
        sigma_px = _noise_px(image, AUTO, {}, "sigma_px", factor=2.0)
        sigma0_mm = max(0.1, sigma_px * 25.4 / image.dpi)
    r["sigma0_mm"] = float(sigma0_mm)
    acc = _shading.multiscale_mean_curvature_shading(
        image.normals, image.dpi, mask=image.mask, scales=scales, sigma0_mm=float(sigma0_mm),
        sigma_ratio=sigma_ratio, gain=1.0, detail=detail, raw=True, origin=image.attrs.get("tile_origin", (0, 0)))
    if isinstance(gain, (int, float)) and gain < 0:
        gain = AUTO
    # the sum is not symmetric about 0 (coarse scales add a bias): its 5th / 95th percentiles are
    # drawn at 0.2 / 0.8; a number for gain keeps 0 = flat at 0.5 and draws 1 / gain at 0.8
    if _is_auto(gain):
        lo, hi = _range(acc, image.mask, AUTO, r, "gain", clip_percent=5.0)
    elif isinstance(gain, (list, tuple)):
        lo, hi = _range(acc, image.mask, gain, r, "gain")
    else:
        lo, hi = -1.0 / float(gain), 1.0 / float(gain)
        r["gain"] = float(gain)
    return _cover(image, _enhance.tone_curve(acc, lo, hi), r)


def draw_discontinuity_lines(image: RGBNImage, threshold_deg: float = 20.0, softness_deg: float = 10.0,
                             outline: bool = True, width_px: float = 1.5, flash_gain: float = 2.5,
                             line_colour=(0.0, 0.0, 0.0), sigma_px="auto", min_length_px="auto") -> Layer:
    """Lines along normal and depth discontinuities (flash map if any) and the outline (§7.3.3);
    the normals are smoothed at the noise scale first, so noise does not draw lines."""
    r = {}
    n = None
    s = _noise_px(image, sigma_px, r, "sigma_px")
    if image.normals is not None:
        n = _smoothed(image, s)
    length = int(round(max(10.0, 10 * s))) if _is_auto(min_length_px) else int(min_length_px)
    r["min_length_px"] = length
    return _ink(_lines.discontinuity_lines(n, mask=image.mask, discontinuity=image.discontinuity,
                                           threshold_deg=threshold_deg, softness_deg=softness_deg,
                                           outline=outline, width_px=width_px, flash_gain=flash_gain,
                                           min_length_px=length), line_colour, r)


def draw_suggestive_contours(image: RGBNImage, radius_px: float = 4.0, fraction: float = 0.2, depth: float = 0.02,
                             min_length_px: int = 12, sigma_px="auto", width_px: float = 1.0,
                             fade_deg: float = 25.0, line_colour=(0.0, 0.0, 0.0), level="auto") -> Layer:
    """Image-space suggestive contours (DeCarlo et al. 2003), faded where the surface faces the viewer (§7.3.4)."""
    r = {}
    s = _noise_px(image, sigma_px, r, "sigma_px", factor=2.0)
    n = _levelled(image, level, r)  # "facing the viewer" relative to a near-flat surface's plane
    return _ink(_lines.suggestive_contours(n, mask=image.mask, radius_px=radius_px, fraction=fraction,
                                           depth=depth, min_length_px=min_length_px, sigma_px=s,
                                           width_px=width_px, fade_deg=fade_deg), line_colour, r)


def draw_suggestive_contours_object(image: RGBNImage, sigma_px="auto", threshold: float = 0.05,
                                    min_length_px: int = 20, width_px: float = 1.0, fade_deg: float = 25.0,
                                    line_colour=(0.0, 0.0, 0.0), level="auto") -> Layer:
    """Object-space suggestive contours from curvature derivatives, faded where facing the viewer (§7.3.4)."""
    r = {}
    s = _noise_px(image, sigma_px, r, "sigma_px", factor=2.0, floor=2.0)
    n = _levelled(image, level, r)
    return _ink(_lines.suggestive_contours_object(n, image.dpi, mask=image.mask, sigma_px=s,
                                                  threshold=threshold, min_length_px=min_length_px,
                                                  width_px=width_px, fade_deg=fade_deg), line_colour, r)


def draw_ridges_valleys(image: RGBNImage, sigma_px="auto", threshold="auto", percentile: float = 97.0,
                        min_length_px="auto", width_px: float = 1.0, ridges: bool = True, valleys: bool = True,
                        ridge_colour=(0.55, 0.1, 0.05), valley_colour=(0.0, 0.0, 0.0)) -> Layer:
    """Ridge (convex crest) and valley (trough) lines at a scale from the noise (2x, >= 1.5 px),
    each with its own switch and colour; "auto" threshold = the percentile of |k| (§7.3.4)."""
    r = {}
    s = _noise_px(image, sigma_px, r, "sigma_px", factor=2.0, floor=1.5)
    length = int(round(10 * s)) if _is_auto(min_length_px) else int(min_length_px)
    r["min_length_px"] = length
    if isinstance(threshold, (int, float)) and threshold < 0:
        threshold = AUTO
    ridge, valley, t = _lines.ridges_valleys(image.normals, image.dpi, mask=image.mask, sigma_px=s,
                                             threshold=None if _is_auto(threshold) else float(threshold),
                                             percentile=percentile, min_length_px=length, width_px=width_px,
                                             return_threshold=True)
    r["threshold"] = float(t)
    if not ridges:
        ridge = np.zeros_like(ridge)
    if not valleys:
        valley = np.zeros_like(valley)
    alpha = np.maximum(ridge, valley)
    rgb = np.where((valley >= ridge)[..., None], np.asarray(valley_colour, np.float32),
                   np.asarray(ridge_colour, np.float32)).astype(np.float32)
    return Layer(rgb, alpha, r)


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
                     seed: int = 0, colour_exposure="auto", lightness="auto") -> Layer:
    """Watercolour: bilateral-flattened washes, relief density, paper texture, edge darkening (§7.3.8);
    a picture whose lightness is narrow is then spread over the tone range (the washes flatten a
    narrow colour further: the flatbed coin's used 49.9 % of it)."""
    from common.rgbn.bilateral import joint_bilateral

    r = {}
    washes, _ = joint_bilateral(image.albedo, image.normals, sigma_x=sigma_x, sigma_c=sigma_c,
                                sigma_n=sigma_n if image.normals is not None else np.inf, mask=image.mask,
                                filter_normals=False)     # only the washes are drawn
    shown = _exposed_colour(replace(image, albedo=washes), colour_exposure, r, "colour_exposure")
    out = _paint.watercolour(shown, image.normals, light, mask=image.mask, relief=relief, paper=paper,
                             edge_darkening=edge_darkening, seed=seed, origin=image.attrs.get("tile_origin", (0, 0)))
    return _cover(image, _exposed_lightness(out, image.mask, lightness, r), r)


def draw_segment_boundaries(image: RGBNImage, labels=None, width_px: float = 1.0,
                            line_colour=(0.0, 0.0, 0.0)) -> Layer:
    """Lines between the recipe's colour+normal segments (a [segmentation] section; --style adds one)."""
    if labels is None:
        raise ValueError("style 'segment_boundaries' needs a [segmentation] section in the recipe")
    edge = np.zeros(labels.shape, bool)
    edge[:, 1:] |= labels[:, 1:] != labels[:, :-1]
    edge[1:] |= labels[1:] != labels[:-1]
    edge &= image.mask
    return _ink(_lines._thicken(edge.astype(np.float32), width_px), line_colour)


def draw_normals(image: RGBNImage) -> Layer:
    """The normal map as colour (OpenGL convention, (n + 1) / 2)."""
    return _cover(image, (image.normals + 1.0) * 0.5)


_N, _C = frozenset({"normal"}), frozenset({"colour"})
_NC = frozenset({"normal", "colour"})
STYLES: dict[str, Style] = {s.name: s for s in (
    Style("albedo", draw_albedo, _C, draw_albedo.__doc__),
    Style("colour_relief", draw_colour_relief, _N, draw_colour_relief.__doc__),
    Style("normal_unsharp", draw_normal_unsharp, _N, draw_normal_unsharp.__doc__),
    Style("specular", draw_specular, _N, draw_specular.__doc__),
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

#: Meaning and unit of every style parameter (``tessera render --list-styles`` and docs/gallery.md
#: print them). "auto" values are chosen from the data and reported in ``Rendering.resolved``.
PARAM_DOCS = {
    "light": "light direction: [azimuth_deg, elevation_deg] (azimuth counter-clockwise from the image's right, "
             "elevation above the image plane) or a 3-vector (x right, y up, z to the viewer)",
    "azimuth_deg": "raking light azimuth, degrees counter-clockwise from the image's right (135 = upper left)",
    "elevation_deg": "raking light elevation above the surface, degrees (5-20 rakes)",
    "ambient": "share of the light reaching every pixel, 0-1",
    "colour": "true: draw on the fragment's colour; false: grey",
    "exposure": '"auto" (from robust percentiles of the drawing: lightness 5th/95th -> L* 20/80, or shading '
                '5th/95th -> 0.2/0.8), "none" (as computed), or [low, high] in the style\'s own units',
    "colour_exposure": '"auto": the colour\'s CIELAB lightness, 5th/95th percentiles drawn at L* 20/80 (hue and '
                       'chroma kept; a colour varying less than 15 L* is stretched as it is unless that is under '
                       '6 L* or 10 x its pixel noise); "none": the colour as captured; or [low, high] in L* (0-100)',
    "lightness": '"auto": a drawn picture whose CIELAB lightness spans less than 55 L* between its 5th and 95th '
                 'percentiles gets them drawn at L* 20/80 (hue and chroma kept), a wider one is left as drawn; '
                 '"none": as drawn; or [low, high] in L* (0-100)',
    "sigma_px": 'smoothing of the normals (Gaussian sigma, pixels); "auto" = the scale that brings the map\'s '
                'noise to 0.004 (>= 2 px with JPEG blocks; x2 for gooch, suggestive_contours, '
                'suggestive_contours_object (>= 2 px) and ridges_valleys (>= 1.5 px), x3 for toon)',
    "sigma_mm": "scale of the relief drawn, mm: detail finer than this is enhanced (unsharp masking), or the "
                'curvature scale; "auto" = from the noise',
    "sigma0_px": 'finest scale of exaggerated shading, pixels; "auto" = from the noise',
    "sigma0_mm": 'finest curvature scale, mm; "auto" = from the noise (>= 0.1 mm)',
    "sigma_ratio": "factor between consecutive scales (> 1)",
    "scales": "number of scales",
    "level": '"auto" / true / false / sigma in pixels: light a near-flat surface relative to its own slow '
             'undulation (a painting tilted by near lights); "auto" does it when the coarse normals all point '
             'nearly one way',
    "fine_px": 'noise smoothing before the detail is taken, pixels; "auto" = from the noise',
    "strength": "share of the room to black/white the strongest relief uses (colour_relief, exaggerated with "
                "colour), or the shadow's darkness (discontinuity_shadows), 0-1; colour_relief \"auto\": 0.6, "
                "up to 0.95 for a uniform material (colour lightness spread < 30 L*)",
    "detail_scale": 'detail shading drawn at 0.8 of the strength (its 95th percentile when "auto")',
    "tones": 'exaggerated shading values drawn at 0.2 / 0.8: [low, high], "auto" = 5th / 95th percentiles',
    "gain": "normal_unsharp: RTIViewer's enhancement gain (>= 0); multiscale_mean_curvature: 1 / the curvature "
            'sum drawn at 0.8, or "auto" (5th/95th percentiles drawn at 0.2/0.8)',
    "radius_mm": 'radius of curvature drawn at 0.8 (convex) / 0.2 (concave), mm; "auto" = 90th percentile of |H|',
    "kd": "diffuse weight of specular enhancement (RTIViewer kd), >= 0",
    "ks": "specular weight (RTIViewer ks), >= 0",
    "exponent": "specular exponent (RTIViewer n), > 0: larger = tighter highlights",
    "levels": "number of toon bands (>= 2)",
    "softness": "half-width of a toon band edge, in units of n.l",
    "dark": "brightness of the darkest toon band, 0-1",
    "n_colours": "k-means colours of toon shading (0 = grey)",
    "seed": "random seed (k-means, paper texture): the picture is deterministic",
    "palette": 'toon colours: "auto" (k-means) or a list of RGB colours',
    "blue": "Gooch cool colour's blue, 0-1",
    "yellow": "Gooch warm colour's yellow, 0-1",
    "alpha": "Gooch: share of the object's colour in the cool tone, 0-1",
    "beta": "Gooch: share of the object's colour in the warm tone, 0-1",
    "contrast": "exaggerated shading's a: larger = more toon-like (> 0)",
    "detail": "exponent of the per-scale weights sigma^-detail (0 = all scales equal)",
    "base_weight": "weight of the coarsest lighting in exaggerated shading",
    "threshold": "ridges_valleys: minimum |principal curvature|, 1/mm (\"auto\" = the percentile); "
                 "suggestive_contours_object: minimum cosine between w and grad kr, 0-1",
    "percentile": "percentile of |curvature| used as the automatic threshold, 0-100",
    "min_length_px": 'shortest line piece kept, pixels ("auto" = 10 x sigma_px)',
    "width_px": "drawn line width, pixels (anti-aliased)",
    "ridges": "draw ridge lines (convex crests)",
    "valleys": "draw valley lines (troughs, incisions)",
    "ridge_colour": "RGB of ridge lines, 0-1 each",
    "valley_colour": "RGB of valley lines, 0-1 each",
    "line_colour": "RGB of the lines, 0-1 each",
    "fade_deg": "lines fade where the surface faces the viewer: full strength from this many degrees of turn, "
                "none facing it (0 = no fading)",
    "radius_px": "radius of the image-space valley test, pixels",
    "fraction": "maximum share of darker neighbours of a suggestive-contour pixel, 0-1",
    "depth": "minimum depth of the valley in nz units",
    "threshold_deg": "normal change per pixel at which a discontinuity line is half strength, degrees",
    "softness_deg": "half-width of that ramp, degrees",
    "outline": "draw the fragment's outline",
    "flash_gain": "scale of the flash discontinuity map's strength",
    "length_px": "length of a discontinuity shadow, pixels",
    "softness_px": "blur of the shadow, pixels",
    "steep_nz": "normals with nz below this cast shadows (steep walls)",
    "sigma_x": "spatial sigma of the watercolour's bilateral washes, pixels",
    "sigma_c": "colour sigma of the washes (linear RGB units)",
    "sigma_n": "normal sigma of the washes",
    "relief": "strength of the relief in the watercolour's pigment density",
    "paper": "strength of the paper texture (periodic every 1024 px)",
    "edge_darkening": "strength of pigment gathering at the edges of washes",
}

#: Line and shadow styles: ink over whatever lies below (``--style`` draws them on the colour).
INK_STYLES = ("discontinuity_lines", "suggestive_contours", "suggestive_contours_object", "ridges_valleys",
              "discontinuity_shadows", "segment_boundaries")


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
        defaults = style.parameters()
        bad = params - set(defaults)
        if bad:
            raise ValueError(f"{lw}: style {style.name!r} has no parameter(s) {sorted(bad)}; "
                             f"it takes {', '.join(defaults) or 'none'}")
        for name in sorted(params):
            problem = _type_problem(layer[name], defaults[name], name)
            if problem:
                raise ValueError(f"{lw}: style {style.name!r} parameter {name!r} {problem}, got {layer[name]!r}")


#: "auto" parameters that also take true / false (levelling on or off)
_SWITCHES = frozenset({"level"})
#: "auto" parameters that also take "none" (drawn as computed, the colour as captured)
_NONE_OK = frozenset({"exposure", "colour_exposure", "lightness"})


def _type_problem(value, default, name: str = "") -> str | None:
    """Why ``value`` cannot stand for the parameter ``name`` whose default is ``default`` (None if
    it can)."""
    def number(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)

    if isinstance(value, str) and value == AUTO and isinstance(default, str) and default == AUTO:
        return None
    if isinstance(default, str) and default == AUTO:
        # "auto" or what the style resolves it to: a number, or a list of numbers / of lists
        if number(value) or (isinstance(value, (list, tuple)) and value and all(
                number(x) or (isinstance(x, (list, tuple)) and all(number(y) for y in x)) for x in value)):
            return None
        if name in _SWITCHES:
            return None if isinstance(value, bool) else 'must be "auto", true, false or a number'
        if name in _NONE_OK:
            return None if _is_none(value) else 'must be "auto", "none" or a [low, high] pair'
        return 'must be "auto" or a number (or a list of numbers)'
    if isinstance(default, bool):
        return None if isinstance(value, bool) else "must be true or false"
    if isinstance(default, int):
        return None if number(value) and float(value) == int(value) else "must be a whole number"
    if isinstance(default, float):
        return None if number(value) else "must be a number"
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)) or not all(number(x) for x in value):
            return "must be a list of numbers"
        if len(default) == 2 and len(value) in (2, 3):
            return None  # a light: [azimuth_deg, elevation_deg] or a 3-vector
        if len(default) == 3 and (len(value) != 3 or not all(0 <= x <= 1 for x in value)):
            return "must be an RGB colour: three numbers in [0, 1]"
        return None if len(value) == len(default) else f"must be a list of {len(default)} numbers"
    return None


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
    if style in INK_STYLES:
        layers.insert(0, {"style": "albedo"})
    segmentation = dict(DEFAULT_SEGMENTATION) if "segments" in STYLES[style].needs else None
    recipe = Recipe(name=style, layers=layers, segmentation=segmentation)
    recipe.source = recipe_to_toml(recipe)
    return recipe


#: The [segmentation] a recipe gets from ``style_recipe("segment_boundaries")``.
DEFAULT_SEGMENTATION = {"scale": 400.0, "sigma_px": 1.0, "min_size": 400}


@dataclass
class Rendering:
    """A drawn illustration: display RGB and coverage, on the input's pixel grid — floats in [0, 1] when drawn
    whole, or integers at the recipe's ``bits`` (uint8 / uint16, full scale = 1) when an image too large for one
    tile was drawn tile by tile in bounded memory (:func:`common.render.tiles.render_tiled`).

    ``resolved`` holds, per drawn layer, the values its "auto" parameters took (see
    :class:`Layer`)."""

    rgb: np.ndarray
    alpha: np.ndarray
    recipe: Recipe
    skipped: list = field(default_factory=list)
    resolved: list = field(default_factory=list)


def render(image: RGBNImage, recipe: Recipe | str, *, progress: Callable[[float, str], None] | None = None,
           resolved: list | None = None, tile: int | None = None, warn_skipped: bool = True) -> Rendering:
    """Draw ``image`` with a recipe (or a recipe name / file / style name).

    Layers whose style needs normals are skipped (and listed in ``Rendering.skipped``) for a
    colour-only image; where no colour layer remains the albedo is drawn, under the lines left
    (:func:`layers_without`). One warning names the skipped styles,
    unless ``warn_skipped`` is False: a caller that reports them itself (the renderer service names
    the fragment and face) gets them in ``Rendering.skipped`` only. Images larger than one tile are drawn
    tile by tile in bounded memory (:func:`common.render.tiles.render_tiled`); ``tile`` sets the
    tile side (None: :data:`common.render.tiles.TILE_MPX` decides).

    Parameters
    ----------
    resolved : list of dict, optional
        Per layer, values for its "auto" parameters (``Rendering.resolved`` of an earlier
        drawing): the tiles of one image share them.

    References
    ----------
    Toler-Franklin 2011, §7.3 and Fig. 7.15 (per-segment styles).
    """
    from common.render._heap import reuse_freed_memory

    if isinstance(recipe, str):
        recipe = style_recipe(recipe) if recipe in STYLES else load_recipe(recipe)
    if not isinstance(image, RGBNImage):
        raise ValueError(f"image must be an RGBNImage, got {type(image).__name__}")
    drawn = None
    if resolved is None:
        from common.render.tiles import needs_tiles, render_tiled

        if needs_tiles(image, recipe, tile):   # each tile reuses its own freed arrays
            drawn = render_tiled(image, recipe, tile=tile, progress=progress)
    if drawn is None:
        with reuse_freed_memory():   # freed arrays are reused, not page-faulted in again (_heap)
            drawn = _render_whole(image, recipe, progress, resolved)
    if drawn.skipped and warn_skipped:   # once per drawing, not per tile (the drawing of a tile says nothing)
        log.warning("image has no normals: skipped %s", ", ".join(drawn.skipped))
    return drawn


def _render_whole(image, recipe, progress, resolved, labels=None, coarse=None, core=None) -> Rendering:
    """Draw one image (or one tile) in memory; the per-image cache lives for this call only.
    ``labels``: the recipe's segments on this window (a tile gets its window of the whole
    image's), None to segment the image here. ``coarse``: {sigma: Coarse}, this window of the
    whole image's coarse normal fields for levelling (:func:`common.render.enhance.coarse_window`).
    ``core``: (r0, r1, c0, c1), the pixels of the drawing that are kept (a tile's core): the
    per-segment layers are drawn only for those (None: all)."""
    _cache.clear()
    for sigma, field in (coarse or {}).items():
        _cache[("whole coarse", float(sigma))] = field
    try:
        return _render_image(image, recipe, progress, resolved, labels, core)
    finally:
        _cache.clear()


#: A per-segment layer is drawn over windows around the pixels it shows (:func:`_draw_where_shown`)
#: when they hold at most this share of the image; else over the whole image.
WINDOW_SHARE = 0.6
#: Styles whose drawing on a window, given the whole image's "auto" values and coarse fields,
#: is the whole drawing's on the window's core (tests/render/test_recipes.py) ...
_WINDOWED = frozenset({"albedo", "toon", "normals", "lambertian", "raking", "gooch", "exaggerated", "specular",
                       "mean_curvature", "multiscale_mean_curvature", "colour_relief", "normal_unsharp"})
#: ... and those of them whose "auto" values are all statistics of the image's inputs, taken from
#: the whole image through :func:`_whole` (never of what they draw): they are drawn on windows
#: even when the values are not given (the others only in tiles, which are given them).
_INPUT_AUTO = frozenset({"albedo", "toon", "normals"})


def _draw_where_shown(image, recipe, layer, params, shown) -> Layer | None:
    """A shading layer drawn only over windows around the pixels ``shown`` ((H, W) bool: its
    segments on the fragment, within the kept core), each with the style's own reach as a margin
    (:func:`common.render.tiles.halo_px`), so the values there are those of a drawing of the whole
    image; elsewhere nothing (alpha 0). The "auto" values are the whole image's: given (tiles),
    or, for a style of :data:`_INPUT_AUTO`, picked from the whole image's statistics by a first
    drawing of a small window. None when the layer must be drawn whole (a style not known to draw
    the same on windows, "auto" values that come from its own drawing, or windows that would
    cover more than :data:`WINDOW_SHARE` of the image)."""
    from common.render.tiles import MemorySource, halo_px, shown_windows

    style = STYLES[layer["style"]]
    if style.name not in _WINDOWED:
        return None
    if any(_is_auto(v) for v in {**style.parameters(), **params}.values()) and style.name not in _INPUT_AUTO:
        return None
    h, w = image.shape
    source = MemorySource(image)
    cores = shown_windows(shown, 0)

    def draw(r0, r1, c0, c1, values):
        sub = source.window(r0, r1, c0, c1)
        _cache["window"] = (image, sub, (r0, c0))
        share, _cache["share_smoothed"] = _cache.get("share_smoothed"), False   # a window's are its own
        try:
            return style.draw(sub, **values)
        finally:
            _cache["window"] = None
            _cache["share_smoothed"] = share

    # the values of the "auto" parameters (and the resolved values to report) from a small window
    r0, _, c0, _ = cores[0][0] if cores else (0, 0, 0, 0)
    r0, c0 = min(r0, max(0, h - 32)), min(c0, max(0, w - 32))
    chosen = dict(draw(r0, min(h, r0 + 32), c0, min(w, c0 + 32), params).resolved)
    values = {**params, **{k: v for k, v in chosen.items() if k in style.parameters()}}
    level = values.get("level")
    margin = halo_px(replace(recipe, layers=[layer], preprocess={}), image.dpi, [values],
                     whole_levels={float(level)} if isinstance(level, (int, float)) else ())
    windows = shown_windows(shown, margin)
    if sum((b - a) * (d - c) for _, (a, b, c, d) in windows) > WINDOW_SHARE * h * w:
        return None
    rgb = np.zeros((h, w, 3), np.float32)
    alpha = np.zeros((h, w), np.float32)
    for (a, b, c, d), (wa, wb, wc, wd) in windows:
        drawn = draw(wa, wb, wc, wd, values)
        core = (slice(a - wa, b - wa), slice(c - wc, d - wc))
        rgb[a:b, c:d] = drawn.rgb[core]
        alpha[a:b, c:d] = drawn.alpha[core]
        del drawn
    return Layer(rgb, alpha, chosen)


def layers_without(layers: list[dict], skipped) -> list[dict]:
    """The layers a colour-only image is drawn with: those of a ``skipped`` style left out, and the albedo
    as captured first where no colour layer is left (lines alone would be drawn on the blank background: the
    default recipe made a white silhouette of every imported picture), or alone where nothing is left. As
    captured, not exposed: the automatic exposure draws the 5th lightness percentile at L* 20, which turns a
    pale plaster's pink band near black (RePAIR), and an imported picture is already what its maker saw.

    >>> [layer["style"] for layer in layers_without([{"style": "colour_relief"}, {"style": "discontinuity_lines"}],
    ...                                             ["colour_relief"])]
    ['albedo', 'discontinuity_lines']
    """
    kept = [layer for layer in layers if layer["style"] not in skipped]
    if not any(layer["style"] not in INK_STYLES for layer in kept):
        kept = [{"style": "albedo", "exposure": "none"}, *kept]
    return kept


def _render_image(image, recipe, progress, resolved, labels=None, core=None) -> Rendering:
    image = _preprocess(image, recipe.preprocess)
    layers = recipe.layers
    skipped = [layer["style"] for layer in layers if "normal" in STYLES[layer["style"]].needs and image.normals is None]
    if skipped:   # reported by the caller (render, or the renderer service), once per image, not per tile
        layers = layers_without(layers, skipped)
    if labels is None and any("segments" in layer or "exclude_segments" in layer
                              or "segments" in STYLES[layer["style"]].needs for layer in layers):
        from common.rgbn.segmentation import segment_rgbn

        labels = segment_rgbn(image.albedo, image.normals, mask=image.mask, **(recipe.segmentation or {}))
    # the canvas and the coverage are made after the first layer is drawn, from the memory its
    # temporaries freed (_heap), so they do not raise the drawing's peak; a first layer that
    # covers all or nothing of each pixel is itself the canvas (_adopt_as_canvas)
    canvas = cover = None
    chosen = []
    # layers share the normals they smooth at the same scale (kept for this drawing only)
    _cache["share_smoothed"] = len(layers) > 1
    for i, layer in enumerate(layers):
        if progress:
            progress(i / len(layers), f"drawing {layer['style']}")
        style = STYLES[layer["style"]]
        params = {k: (tuple(v) if isinstance(v, list) else v) for k, v in layer.items() if k not in _LAYER_KEYS}
        if resolved is not None and i < len(resolved):
            params.update({k: v for k, v in resolved[i].items() if k in params or k in style.parameters()})
        if "segments" in style.needs:
            params["labels"] = labels
        shown = None   # where a per-segment layer shows
        if labels is not None and ("segments" in layer or "exclude_segments" in layer):
            shown = _in_segments(labels, layer["segments"]) if "segments" in layer else np.ones(labels.shape, bool)
            if "exclude_segments" in layer:
                shown &= ~_in_segments(labels, layer["exclude_segments"])
        drawn = None
        if shown is not None and layer["style"] not in INK_STYLES:   # a shading style covers the mask
            on = shown & image.mask
            if core is not None:
                kept = np.zeros(on.shape, bool)
                kept[core[0]:core[1], core[2]:core[3]] = True
                on &= kept
            drawn = _draw_where_shown(image, recipe, layer, params, on)
            del on
        if drawn is None:
            drawn = style.draw(image, **params)
        chosen.append(dict(drawn.resolved))
        a = drawn.alpha * np.float32(layer["opacity"]) if layer.get("opacity", 1.0) != 1.0 else drawn.alpha
        if shown is not None:
            a = a * shown
        del shown
        a = a.astype(np.float32, copy=False)
        blend = layer.get("blend", "normal")
        if canvas is None:
            cover = np.zeros(image.shape, np.float32)
            canvas = _adopt_as_canvas(drawn.rgb, a, blend, image, recipe.background)
            if canvas is None:
                canvas = np.empty(image.shape + (3,), np.float32)
                canvas[:] = np.asarray(recipe.background, np.float32)
                canvas = _blend(canvas, drawn.rgb, a, blend)
        else:
            canvas = _blend(canvas, drawn.rgb, a, blend)
        del drawn
        np.maximum(cover, a, out=cover)
    if progress:
        progress(1.0, "done")
    np.clip(canvas, 0.0, 1.0, out=canvas)
    np.maximum(cover, image.mask, out=cover)
    return Rendering(canvas, np.clip(cover, 0.0, 1.0, out=cover), recipe, skipped, chosen)


def _in_segments(labels: np.ndarray, segments) -> np.ndarray:
    """(H, W) bool: the pixels whose label is one of ``segments`` (``np.isin``, as one comparison
    per segment: a recipe names a few, and numpy's isin sorts the image's labels for them)."""
    out = np.zeros(labels.shape, bool)
    for s in segments:
        out |= labels == s
    return out


def _adopt_as_canvas(rgb, alpha, blend: str, image: RGBNImage, background):
    """The first layer's own colour array made the canvas, with the background put where the layer
    does not cover: what a normal blend onto the background gives when the coverage is all or
    nothing (a shading style on its mask), without a canvas of its own to fill and copy into.
    None when that does not apply (another blend, partial coverage, an array the image or the
    drawing's cache also holds)."""
    if blend != "normal" or not isinstance(rgb, np.ndarray) or rgb.dtype != np.float32 \
            or rgb.shape != image.shape + (3,) or not rgb.flags.c_contiguous or not rgb.flags.writeable:
        return None
    held = [image.albedo, image.normals, image.mask] + [v for v in _cache.values() if isinstance(v, np.ndarray)]
    if any(x is not None and np.may_share_memory(rgb, x) for x in held):
        return None
    from common.rgbn.smoothing import copy_where, strips

    off = alpha <= 0.0
    if np.count_nonzero(alpha >= 1.0) + np.count_nonzero(off) != alpha.size:
        return None
    # the background put a strip at a time (a masked copy of one strip of it: no per-pixel gather)
    spans = [(r0, r1) for r0, r1, _, _ in strips(image.shape, 0)]
    fill = np.empty((spans[0][1],) + rgb.shape[1:], np.float32)   # the first strip is the tallest
    fill[:] = np.asarray(background, np.float32)
    for r0, r1 in spans:
        copy_where(rgb[r0:r1], fill[:r1 - r0], off[r0:r1])
    return rgb


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
    if mode == "normal":
        on = alpha >= 1.0
        if np.count_nonzero(on) + np.count_nonzero(alpha <= 0.0) == alpha.size:
            # coverage is all or nothing (a shading style on its mask): a copy, not a mix
            from common.rgbn.smoothing import copy_where

            return copy_where(base, np.asarray(rgb, np.float32), on)
        del on
        # base + (rgb - base) a in place, a strip of rows at a time, on the rows the layer touches
        # (line and shadow ink covers a few per cent of the image): no temporaries of its size
        from common.rgbn.smoothing import strips

        touched = np.flatnonzero(alpha.any(axis=1))
        if touched.size:
            for r0, r1, _, _ in strips((int(touched[-1]) + 1 - int(touched[0]),) + base.shape[1:], 0):
                rows = slice(int(touched[0]) + r0, int(touched[0]) + r1)
                d = np.subtract(rgb[rows], base[rows], dtype=np.float32)
                d *= alpha[rows][..., None]
                base[rows] += d
        return base
    a = alpha[..., None]
    if mode == "multiply":
        top = base * rgb
    elif mode == "screen":
        top = 1.0 - (1.0 - base) * (1.0 - rgb)
    elif mode == "darken":
        top = np.minimum(base, rgb)
    elif mode == "lighten":
        top = np.maximum(base, rgb)
    elif mode == "overlay":
        top = np.where(base <= 0.5, 2.0 * base * rgb, 1.0 - 2.0 * (1.0 - base) * (1.0 - rgb))
    elif mode == "soft_light":
        # W3C Compositing Level 1 soft-light
        d = np.where(base <= 0.25, ((16.0 * base - 12.0) * base + 4.0) * base, np.sqrt(base))
        top = np.where(rgb <= 0.5, base - (1.0 - 2.0 * rgb) * base * (1.0 - base),
                       base + (2.0 * rgb - 1.0) * (d - base))
    elif mode == "lightness":
        # the layer's grey (0.5 = none) as relief on the lightness of what lies below (CIELAB L*)
        from common.rgbn.io import srgb_to_linear

        relief = 2.0 * rgb.mean(axis=2) - 1.0
        top = _enhance.lightness_relief(srgb_to_linear(np.clip(base, 0.0, 1.0)), relief, strength=0.7)
    else:
        raise ValueError(f"blend must be one of {BLENDS}, got {mode!r}")
    return base + (top - base) * a
