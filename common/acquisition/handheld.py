"""Hand-held flash capture → RGBN image (thesis §3.2).

For objects too big or fragile for the flatbed: a fixed camera, a flash moved by hand, and a
mirror sphere and a diffuse sphere in the frame (or a light file from an RTI capture). This
module reads such captures (8/16-bit PNG, TIFF, JPEG), puts the pieces together —

1. light directions from a light file (:mod:`.lightfile`) or the mirror sphere (:mod:`.spheres`),
   relative intensities from the diffuse sphere or an intensity file;
2. normals and RGB albedo by the least-squares or robust solver (:mod:`.photometric`, eq. 3.2);
3. the directional depth-discontinuity map (:mod:`.discontinuity`, Raskar et al. 2004)

— into the same :class:`~common.rgbn.image.RGBNImage` the flatbed path produces, so features
and rendering work on either. It also simulates a flash capture of a
:class:`~common.acquisition.surface.FragmentSurface` (Lambertian + specular, cast shadows) so
the path can be checked end to end without a camera.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from common.acquisition.discontinuity import depth_discontinuities
from common.acquisition.lightfile import LightSet
from common.acquisition.photometric import least_squares_normals, robust_normals
from common.acquisition.spheres import diffuse_sphere_intensities, mirror_sphere_directions
from common.acquisition.surface import FragmentSurface
from common.rgbn.image import RGBNImage
from common.rgbn.io import encode_normal_map, linear_to_srgb, srgb_to_linear, write_image

METHODS = ("robust", "least_squares")

#: Algorithm version of the hand-held path: part of the content key of its RGBN artifacts.
VERSION = "handheld-ps-1"


def read_images(paths: Sequence[str | os.PathLike], *, srgb: bool = False,
                saturation: float = 0.995) -> tuple[np.ndarray, np.ndarray]:
    """Read one view's flash images (8/16-bit PNG or TIFF, JPEG; grey, RGB or RGBA).

    Parameters
    ----------
    paths : sequence of paths
        Image files, all of the same size.
    srgb : bool
        Decode the sRGB transfer curve to linear intensities (camera JPEGs). Raw-developed
        16-bit TIFF/PNG are usually linear already (default).
    saturation : float
        A pixel whose brightest channel reaches this fraction of full scale is saturated.

    Returns
    -------
    images : (N, H, W, 3) float32
        Linear RGB in [0, 1] (full scale of the file's bit depth = 1).
    saturated : (N, H, W) bool
        Clipped measurements, to exclude from the solve.
    """
    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise ValueError("paths is empty: give at least 3 images")
    images, shape = None, None
    for i, p in enumerate(paths):
        raw = cv2.imread(p, cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"cannot read image {p} (missing or not PNG/TIFF/JPEG)")
        if raw.dtype == np.uint8:
            scale = 255.0
        elif raw.dtype == np.uint16:
            scale = 65535.0
        elif np.issubdtype(raw.dtype, np.floating):
            scale = 1.0
        else:
            raise ValueError(f"image {p} has unsupported sample type {raw.dtype} (8/16-bit or float)")
        if raw.ndim == 2:
            raw = np.repeat(raw[..., None], 3, axis=2)
        elif raw.ndim == 3 and raw.shape[2] == 4:
            raw = raw[..., :3]
        if raw.ndim != 3 or raw.shape[2] != 3:
            raise ValueError(f"image {p} has shape {raw.shape}: expected grey, RGB or RGBA")
        if shape is None:
            shape = raw.shape[:2]
            images = np.empty((len(paths),) + shape + (3,), np.float32)
        elif raw.shape[:2] != shape:
            raise ValueError(f"image {p} is {raw.shape[1]}x{raw.shape[0]}, the first is {shape[1]}x{shape[0]}: "
                             "all images of a view must have the same size")
        images[i] = raw[..., ::-1] / np.float32(scale)  # OpenCV gives BGR
    saturated = images.max(axis=3) >= saturation
    if srgb:
        images = srgb_to_linear(images)
    return images, saturated


def read_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask image (non-zero = object) as (H, W) bool, checking its size."""
    m = cv2.imread(os.fspath(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise ValueError(f"cannot read mask image {path}")
    if m.ndim == 3:
        m = m[..., :3].max(axis=2) if m.shape[2] >= 3 else m[..., 0]
    m = m > 0
    if shape is not None and m.shape != tuple(shape):
        raise ValueError(f"mask {path} is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


def object_mask(images, *, exclude=None) -> np.ndarray:
    """Automatic object mask: Otsu threshold of the max composite, largest region, holes filled.

    Parameters
    ----------
    images : (N, H, W, 3) or (N, H, W) float array
    exclude : (H, W) bool, optional
        Pixels never part of the object (e.g. the calibration spheres).
    """
    a = np.asarray(images, np.float32)
    grey = a.max(axis=0)
    if grey.ndim == 3:
        grey = grey.max(axis=2)
    g = np.sqrt(np.clip(grey, 0, None))
    u8 = np.clip(g / max(float(g.max()), 1e-12) * 255, 0, 255).astype(np.uint8)
    _, fg = cv2.threshold(u8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    if exclude is not None:
        fg[np.asarray(exclude, bool)] = 0
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n <= 1:
        raise ValueError("no object found against the background; give a mask")
    obj = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    # fill holes: the background is what the border reaches
    flood = np.pad(1 - obj, 1, constant_values=1)
    cv2.floodFill(flood, None, (0, 0), 2)
    return (flood[1:-1, 1:-1] != 2)


def sphere_lights(chrome_images, chrome_circle, *, diffuse_images=None, diffuse_circle=None,
                  diffuse_saturated=None) -> LightSet:
    """Calibrate the flashes from the spheres (thesis §3.2).

    Parameters
    ----------
    chrome_images : (N, H, W[, 3]) array
        Images showing the mirror sphere (the capture itself, or a separate set under the
        same flashes).
    chrome_circle : (cx, cy, r)
        Mirror-sphere outline in pixels.
    diffuse_images, diffuse_circle : optional
        Images showing the diffuse sphere and its outline; with them each flash also gets a
        relative RGB intensity.
    diffuse_saturated : (N, H, W) bool, optional
        Saturated measurements of the diffuse sphere, excluded from the intensity fit.

    Returns
    -------
    LightSet
        Directions from the mirror-sphere highlights, intensities from the diffuse sphere.
    """
    directions = mirror_sphere_directions(chrome_images, chrome_circle)
    intensities = None
    if diffuse_images is not None:
        if diffuse_circle is None:
            raise ValueError("diffuse_circle is required with diffuse_images")
        valid = None if diffuse_saturated is None else ~np.asarray(diffuse_saturated, bool)
        intensities = diffuse_sphere_intensities(diffuse_images, diffuse_circle, directions, valid=valid)
    return LightSet(directions, intensities=intensities)


def handheld_rgbn(images, lights: LightSet | np.ndarray, *, mask=None, saturated=None,
                  method: str = "robust", dpi: float = 96.0, discontinuities: bool = True,
                  progress: Callable[[float, str], None] | None = None, **solver_options) -> RGBNImage:
    """RGBN image of a hand-held flash capture (thesis §3.2).

    Parameters
    ----------
    images : (N, H, W, 3) float array
        Linear flash images of one view (:func:`read_images`).
    lights : LightSet or (N, 3) array
        Light directions (x right, y up, z towards the camera) and optional relative
        intensities; each image is divided by its light's intensity before solving.
    mask : (H, W) bool, optional
        Object pixels (default: :func:`object_mask`).
    saturated : (N, H, W) bool, optional
        Measurements to exclude (from :func:`read_images`).
    method : {'robust', 'least_squares'}
        Normal solver (see :mod:`common.acquisition.photometric`).
    dpi : float
        Sampling density of the view (nominal when the capture has no scale).
    discontinuities : bool
        Also compute the directional depth-discontinuity map (Raskar et al. 2004).
    progress : callable(fraction, text), optional
    **solver_options
        Passed to :func:`~common.acquisition.photometric.robust_normals`.

    Returns
    -------
    RGBNImage
        Normals, RGB albedo, confidence, mask and (optionally) ``discontinuity`` (H, W, 2);
        ``attrs`` record the method, the light count and ``capture = 'handheld-flash'``.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not isinstance(lights, LightSet):
        lights = LightSet(np.asarray(lights, dtype=np.float64))
    imgs = np.asarray(images, dtype=np.float32)
    if imgs.ndim == 3:
        imgs = np.repeat(imgs[..., None], 3, axis=3)
    if imgs.ndim != 4 or imgs.shape[3] != 3:
        raise ValueError(f"images must be (N, H, W, 3), got {imgs.shape}")
    if len(imgs) != len(lights):
        raise ValueError(f"{len(imgs)} images but {len(lights)} lights")
    if lights.intensities is not None:
        imgs = imgs / lights.intensities[:, None, None, :].astype(np.float32)
    valid = None if saturated is None else ~np.asarray(saturated, bool)
    if mask is None:
        mask = object_mask(imgs)
    report = progress or (lambda f, t: None)
    solve_share = 0.85 if discontinuities else 1.0
    sub = lambda f, t: report(solve_share * f, t)  # noqa: E731
    if method == "robust":
        out = robust_normals(imgs, lights.directions, mask=mask, valid=valid, dpi=dpi, progress=sub, **solver_options)
    else:
        if solver_options:
            raise ValueError(f"least_squares takes no solver options, got {sorted(solver_options)}")
        out = least_squares_normals(imgs, lights.directions, mask=mask, valid=valid, dpi=dpi, progress=sub)
    if discontinuities:
        report(solve_share, "depth discontinuities")
        out.discontinuity = depth_discontinuities(imgs, lights.directions, mask=mask)
    out.attrs.update({"capture": "handheld-flash", "lights_calibrated": lights.intensities is not None})
    report(1.0, "done")
    return out


def surface_normals(surface: FragmentSurface) -> np.ndarray:
    """Unit normals (x right, y up, z to viewer) of a surface's height map, (H, W, 3)."""
    h = surface.height_mm.astype(np.float64)
    d_row, d_col = np.gradient(h, surface.pixel_mm)
    # y points up (towards row 0): dh/dy = −dh/drow
    n = np.stack([-d_col, d_row, np.ones_like(h)], axis=-1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def cast_shadows(height_mm, pixel_mm: float, direction) -> np.ndarray:
    """Pixels of a height map in the cast shadow of a distant light, (H, W) bool.

    Marches from every pixel towards the light over the height field (vectorised over pixels,
    one step per pixel of travel) and marks the pixel shadowed when the terrain rises above
    the ray.
    """
    h = np.asarray(height_mm, np.float32)
    l = np.asarray(direction, np.float64)
    l = l / np.linalg.norm(l)
    tilt = float(np.hypot(l[0], l[1]))
    if tilt < 1e-6 or l[2] <= 0:
        return np.zeros(h.shape, bool) if l[2] > 0 else np.ones(h.shape, bool)
    rise = float(l[2] / tilt) * pixel_mm  # ray height gained per pixel travelled (mm)
    span = float(h.max() - h.min())
    steps = int(min(np.ceil(span / max(rise, 1e-9)) + 1, max(h.shape) * 1.5))
    d_col, d_row = float(l[0]) / tilt, -float(l[1]) / tilt
    rows, cols = np.mgrid[0:h.shape[0], 0:h.shape[1]].astype(np.float32)
    shadow = np.zeros(h.shape, bool)
    tol = 0.05 * rise
    for k in range(1, steps + 1):
        terrain = cv2.remap(h, cols + k * d_col, rows + k * d_row, cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=float(h.min()))
        shadow |= terrain > h + k * rise + tol
    return shadow


def simulate_flash_capture(surface: FragmentSurface, directions, *, intensities=None, specular: float = 0.0,
                           shininess: float = 40.0, ambient: float = 0.0, shadows: bool = True,
                           noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """Render flash images of a fragment face: Lambertian + Blinn–Phong highlight + cast shadows.

    Parameters
    ----------
    surface : FragmentSurface
        Albedo, height map (mm) and mask of the face; pixels outside the mask render as the
        flat background at height 0 with albedo 0.05.
    directions : (N, 3) array
        Distant flash directions (x right, y up, z towards the camera).
    intensities : (N,) or (N, 3) array, optional
        Flash intensity (RGB) per image (default 1).
    specular : float
        Weight of the Blinn–Phong term ``specular · (n·h)^shininess`` (orthographic view
        v = (0, 0, 1), h = (l + v)/|l + v|).
    ambient : float
        Constant light added everywhere (also in shadows).
    shadows : bool
        Cast shadows from the height field.
    noise : float
        Standard deviation of additive Gaussian noise.
    seed : int
        Noise seed.

    Returns
    -------
    (N, H, W, 3) float32
        Linear images clipped to [0, 1] (a clipped pixel is what a camera saturates).
    """
    d = np.asarray(directions, np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions must be (N, 3), got {d.shape}")
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n_img = len(d)
    e = np.ones((n_img, 3)) if intensities is None else np.asarray(intensities, np.float64)
    if e.ndim == 1:
        e = np.repeat(e[:, None], 3, axis=1)
    if e.shape != (n_img, 3):
        raise ValueError(f"intensities must be ({n_img},) or ({n_img}, 3), got {e.shape}")
    normals = surface_normals(surface)
    albedo = np.where(surface.mask[..., None], surface.albedo, np.float32(0.05)).astype(np.float32)
    height = np.where(surface.mask, surface.height_mm, 0.0).astype(np.float32)
    rng = np.random.default_rng(seed)
    out = np.empty((n_img,) + albedo.shape, np.float32)
    view = np.array([0.0, 0.0, 1.0])
    for i, l in enumerate(d):
        shade = np.clip(normals @ l.astype(np.float32), 0, None)
        half = (l + view) / np.linalg.norm(l + view)
        spec = specular * np.clip(normals @ half.astype(np.float32), 0, None) ** shininess * (shade > 0)
        lit = (albedo * shade[..., None] + spec[..., None])
        if shadows:
            lit[cast_shadows(height, surface.pixel_mm, l)] = 0.0
        img = lit * e[i].astype(np.float32) + ambient * albedo
        if noise > 0:
            img = img + rng.normal(0.0, noise, img.shape).astype(np.float32)
        out[i] = np.clip(img, 0.0, 1.0)
    return out


def discontinuity_picture(discontinuity) -> np.ndarray:
    """(H, W, 3) colour picture of a discontinuity map: hue = direction to the occluder, value = strength."""
    d = np.asarray(discontinuity, np.float32)
    if d.ndim != 3 or d.shape[2] != 2:
        raise ValueError(f"discontinuity must be (H, W, 2), got {d.shape}")
    strength = np.clip(np.linalg.norm(d, axis=2), 0, 1)
    hue = (np.degrees(np.arctan2(d[..., 1], d[..., 0])) % 360) / 2  # OpenCV hue is 0..180
    hsv = np.stack([hue, np.full_like(hue, 255), strength * 255], axis=2).astype(np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB).astype(np.float32) / 255


def write_pictures(image: RGBNImage, directory: str | os.PathLike, *, prefix: str = "") -> list[str]:
    """Write viewable PNGs of an RGBN image: normals (OpenGL colours), albedo (sRGB), confidence, discontinuity."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    alpha = image.mask.astype(np.float32)
    if image.normals is not None:
        colours = encode_normal_map(image.normals, image.mask)
        written.append(write_image(out / f"{prefix}normals.png", colours, alpha=alpha))
    written.append(write_image(out / f"{prefix}albedo.png", linear_to_srgb(image.albedo), alpha=alpha))
    if image.confidence is not None:
        written.append(write_image(out / f"{prefix}confidence.png", image.confidence))
    if image.discontinuity is not None:
        written.append(write_image(out / f"{prefix}discontinuity.png", discontinuity_picture(image.discontinuity)))
    return [str(p) for p in written]
