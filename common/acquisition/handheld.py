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
from concurrent.futures import ThreadPoolExecutor
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


#: An image with more than this share of saturated pixels is overexposed: refused.
MAX_SATURATED_SHARE = 0.5


def _depth_name(dtype) -> str:
    return {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(np.dtype(dtype), f"{np.dtype(dtype)}")


def _channels_name(raw) -> str:
    return "grey" if raw.ndim == 2 else {1: "grey", 3: "RGB", 4: "RGBA"}.get(raw.shape[2], f"{raw.shape[2]}-channel")


def _convert(raw, path, first, out, sat_out, scale, srgb, saturation):
    """Check one decoded image (RGB(A) order) against the first of the stack; write linear RGB and saturation."""
    if raw.dtype != first.dtype:
        raise ValueError(f"image {path} is {_depth_name(raw.dtype)}, the first image is {_depth_name(first.dtype)}: "
                         "all images of a view must have the same bit depth")
    if _channels_name(raw) != _channels_name(first):
        raise ValueError(f"image {path} is {_channels_name(raw)}, the first image is {_channels_name(first)}: "
                         "all images of a view must have the same channels")
    if raw.shape[:2] != first.shape[:2]:
        raise ValueError(f"image {path} is {raw.shape[1]}x{raw.shape[0]}, the first is "
                         f"{first.shape[1]}x{first.shape[0]}: all images of a view must have the same size")
    if raw.ndim == 3 and raw.shape[2] <= 2:
        raw = raw[..., 0]  # grey (+ alpha)
    if raw.ndim == 2:
        out[...] = (raw / np.float32(scale))[..., None]
        peak = raw
    else:
        np.multiply(raw[..., :3], np.float32(1.0 / scale), out=out, casting="unsafe")
        peak = np.maximum(np.maximum(raw[..., 0], raw[..., 1]), raw[..., 2])  # on the samples: cheaper than floats
    np.greater_equal(peak, saturation * scale if raw.dtype.kind == "f" else np.ceil(saturation * scale - 1e-9),
                     out=sat_out)
    if srgb:
        out[...] = srgb_to_linear(out)
    share = float(sat_out.mean())
    if share > MAX_SATURATED_SHARE:
        raise ValueError(f"image {path} is saturated on {100 * share:.0f}% of its pixels (overexposed)")


def read_images(paths: Sequence[str | os.PathLike], *, srgb: bool = False, saturation: float = 0.995,
                bit_depth: int | None = None, threads: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read one view's flash images (8/16-bit PNG or TIFF, JPEG; grey, RGB or RGBA), checked at the door.

    Parameters
    ----------
    paths : sequence of paths
        Image files, all of the same size, bit depth and channels.
    srgb : bool
        Decode the sRGB transfer curve to linear intensities (camera JPEGs). Raw-developed
        16-bit TIFF/PNG are usually linear already (default).
    saturation : float
        A pixel whose brightest channel reaches this fraction of full scale is saturated.
    bit_depth : {8, 16}, optional
        Declared bit depth of the capture: a file of another depth is refused.
    threads : int, optional
        Decoding threads (default: the CPU count; OpenCV releases the GIL while decoding).

    Returns
    -------
    images : (N, H, W, 3) float32
        Linear RGB in [0, 1] (full scale of the file's bit depth = 1).
    saturated : (N, H, W) bool
        Clipped measurements, to exclude from the solve.

    Raises
    ------
    ValueError
        Naming the file and the reason. Each file goes through the importers' door
        (:func:`common.imports.door.read_image_checked`: missing, truncated, corrupt, 8-bit
        values in a 16-bit file, a depth other than ``bit_depth``, all black, blank); then the
        stack: a bit depth, channel layout or size other than the first image's, more than
        :data:`MAX_SATURATED_SHARE` saturated pixels.

    Notes
    -----
    Files are decoded by a thread pool (the decoders release the GIL) straight into the
    preallocated float32 stack, so the peak memory is the stack plus one decoded file per thread.
    """
    from common.imports.door import read_image_checked

    paths = [os.fspath(p) for p in paths]
    if not paths:
        raise ValueError("paths is empty: give at least 3 images")
    if bit_depth not in (None, 8, 16):
        raise ValueError(f"bit_depth must be 8 or 16, got {bit_depth!r}")
    first = read_image_checked(paths[0], bits=bit_depth)
    n, (h, w) = len(paths), first.pixels.shape[:2]
    images = np.empty((n, h, w, 3), np.float32)
    saturated = np.empty((n, h, w), bool)

    def one(i, checked=None):
        checked = read_image_checked(paths[i], bits=bit_depth) if checked is None else checked
        _convert(checked.pixels, paths[i], first.pixels, images[i], saturated[i], checked.full_scale, srgb,
                 saturation)

    workers = max(1, min(n, threads or os.cpu_count() or 1))
    one(0, first)
    if workers == 1:
        for i in range(1, n):
            one(i)
    else:
        with ThreadPoolExecutor(workers) as pool:
            futures = [pool.submit(one, i) for i in range(1, n)]
            for f in futures:  # the first failure in list order is the one reported
                f.result()
    return images, saturated


def read_mask(path: str | os.PathLike, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a mask image (non-zero = object) as (H, W) bool, checking its size. The file is read
    completely through the import door (:func:`common.imports.door.read_image_checked`): a truncated
    PNG would otherwise come back with its missing rows grey, i.e. object."""
    from common.imports.door import read_image_checked

    m = read_image_checked(path, allow_blank=True).pixels
    if m.ndim == 3:
        m = m[..., :3].max(axis=2) if m.shape[2] >= 3 else m[..., 0]
    m = m > 0
    if shape is not None and m.shape != tuple(shape):
        raise ValueError(f"mask {path} is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


#: The automatic mask refuses (asks for a mask file) when it keeps less than this share of the frame.
MIN_MASK_SHARE = 0.05


def light_modulation(images) -> np.ndarray:
    """How much each pixel's brightness changes with the light: 90th − 10th percentile over the lights.

    Parameters
    ----------
    images : (N, H, W, 3) or (N, H, W) float array
        Linear flash images.

    Returns
    -------
    (H, W) float32
        Modulation of the luminance (BT.601), in the images' units. Constant light (ambient,
        glare on a lid that no flash moves) cancels; a surface the flashes shade has a large
        value whatever its albedo is relative to the rest of the frame, a background that
        receives no light keeps the sensor's noise.
    """
    from common.acquisition.photometric import LUMA

    a = np.asarray(images, np.float32)
    grey = a @ LUMA if a.ndim == 4 else a
    n = len(grey)
    lo, hi = int(0.1 * (n - 1)), int(np.ceil(0.9 * (n - 1)))
    part = np.partition(grey, (lo, hi), axis=0)
    return (part[hi] - part[lo]).astype(np.float32)


def _log_otsu(values, floor):
    """Otsu threshold of log10(values) with everything below ``floor`` lumped at the floor."""
    from skimage.filters import threshold_otsu

    lv = np.log10(np.maximum(values, floor))
    if float(lv.max() - lv.min()) < 1e-6:
        return float(floor)
    return float(10 ** threshold_otsu(lv))


def object_mask(images, *, exclude=None, min_share: float = MIN_MASK_SHARE, info: dict | None = None) -> np.ndarray:
    """Automatic object mask from what varies with the light, not from brightness.

    Parameters
    ----------
    images : (N, H, W, 3) or (N, H, W) float array
        Linear flash images (N ≥ 3).
    exclude : (H, W) bool, optional
        Pixels never part of the object (e.g. the calibration spheres).
    min_share : float in [0, 1)
        A mask keeping less than this share of the frame is refused (ValueError asking for a
        mask file) rather than returned.
    info : dict, optional
        Filled with the figures of the decision (``background``, ``threshold``,
        ``background_level``, ``object_level``, ``top``, ``share``).

    Returns
    -------
    (H, W) bool
        The object: the largest connected region, holes filled.

    Notes
    -----
    1. Per pixel the light modulation *m* (:func:`light_modulation`): a surface the flashes
       shade changes by a share of its albedo; an unlit backdrop only by its noise.
    2. Otsu's threshold on log *m* (values below the 90th percentile of the frame's 2-pixel
       border lumped together, so a backdrop's cast shadows and noise form one class; log scale, so
       dark paint counts by its ratio to the backdrop, not its distance from white).
    3. A background is accepted only if it is one: the lower class's median 5× below the upper
       class's, and the lower class holding at least 75 % of the border (a backdrop surrounds
       the object). The threshold is then the geometric mean of the lower class's 95th and the
       upper class's 5th percentile, or 3× the border's 99th percentile if lower (dark paint
       well above the backdrop stays in). Otherwise the object fills the frame (RTI captures of
       paintings, slabs, coins, dark passages reaching the edge: there is no backdrop to cut
       away) and the mask is every pixel whose modulation exceeds 2 % of the 99th percentile.
    4. Opening (3×3), largest 8-connected region, holes filled (dark paint and cast shadows
       inside the object stay in).

    Raises
    ------
    ValueError
        If nothing is found, or the mask keeps less than ``min_share`` of the frame.

    References
    ----------
    Thesis §3.2 (the object of a hand-held capture). N. Otsu, "A threshold selection method
    from gray-level histograms", IEEE Trans. SMC 9(1), 1979.

    Examples
    --------
    >>> import numpy as np
    >>> L = np.array([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8], [-0.6, 0, 0.8], [0, -0.6, 0.8]])
    >>> n = np.array([0.3, 0.2, 0.93]) / np.linalg.norm([0.3, 0.2, 0.93])
    >>> images = np.full((5, 32, 32), 0.002, np.float32)          # an unlit backdrop
    >>> images[:, 8:24, 8:24] = (0.6 * np.clip(L @ n, 0, None))[:, None, None]
    >>> int(object_mask(images).sum())                              # the 16 x 16 piece
    256
    """
    a = np.asarray(images, np.float32)
    if a.ndim not in (3, 4) or len(a) < 3:
        raise ValueError(f"images must be (N, H, W[, 3]) with N >= 3, got shape {a.shape}")
    if not 0.0 <= min_share < 1.0:
        raise ValueError(f"min_share must be in [0, 1), got {min_share}")
    m = light_modulation(a)
    keep = np.ones(m.shape, bool) if exclude is None else ~np.asarray(exclude, bool)
    top = float(np.percentile(m[keep], 99)) if keep.any() else 0.0
    if top <= 0:
        raise ValueError("nothing in the images changes with the light: no object to find; give a mask")
    ring = np.zeros(m.shape, bool)
    ring[:2], ring[-2:], ring[:, :2], ring[:, -2:] = True, True, True, True
    ring &= keep
    edge = m[ring] if ring.any() else m[keep]
    edge_level, edge_high = float(np.percentile(edge, 90)), float(np.percentile(edge, 99))
    t = _log_otsu(m[keep], max(edge_level, 0.01 * top))
    lower, upper = m[keep & (m <= t)], m[keep & (m > t)]
    bg_level = float(np.median(lower)) if lower.size else 0.0
    fg_level = float(np.median(upper)) if upper.size else top
    border_low = float((edge <= t).mean())
    background = lower.size > 0 and upper.size > 0 and fg_level > 5 * bg_level and border_low >= 0.75
    if background:  # the middle (in log) of the gap between the classes' facing tails, or just above the border
        threshold = min(float(np.sqrt(np.percentile(lower, 95) * np.percentile(upper, 5))), 3 * edge_high)
    else:
        threshold = 0.02 * top
    fg = ((m > threshold) & keep).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if n <= 1:
        raise ValueError("no object found against the background; give a mask")
    obj = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    # fill holes: the background is what the border reaches
    flood = np.pad(1 - obj, 1, constant_values=1)
    cv2.floodFill(flood, None, (0, 0), 2)
    mask = (flood[1:-1, 1:-1] != 2) & keep
    share = float(mask.mean())
    if info is not None:
        info.update(background=bool(background), threshold=float(threshold), background_level=bg_level,
                    object_level=fg_level, top=top, border_background=border_low, share=share)
    if share < min_share:
        raise ValueError(f"the automatic mask covers only {100 * share:.1f}% of the frame (less than "
                         f"{100 * min_share:.0f}%): the object could not be told from the background; "
                         "give a mask image (--mask FILE)")
    return mask


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
                  dome_radius: float | None = None,
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
    dome_radius : float, optional
        Near lights: the lights sit on a dome of this radius (pixels) centred on the image
        centre, at ``dome_radius × direction``; each pixel gets its own light directions and
        1/r² fall-off (:func:`~common.acquisition.photometric.point_light_field`). Default:
        distant lights, unless ``lights.positions`` gives the lights' positions (near lights).
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
    positions = _near_positions(lights, dome_radius)
    where = {"directions": lights.directions} if positions is None else {"positions": positions}
    if method == "robust":
        out = robust_normals(imgs, **where, mask=mask, valid=valid, dpi=dpi, progress=sub, **solver_options)
    else:
        if solver_options:
            raise ValueError(f"least_squares takes no solver options, got {sorted(solver_options)}")
        out = least_squares_normals(imgs, **where, mask=mask, valid=valid, dpi=dpi, progress=sub)
    if discontinuities:
        report(solve_share, "depth discontinuities")
        out.discontinuity = depth_discontinuities(imgs, lights.directions, mask=mask)
    out.attrs.update({"capture": "handheld-flash", "lights_calibrated": lights.intensities is not None})
    if dome_radius is not None:
        out.attrs["dome_radius_px"] = float(dome_radius)
    out.attrs["near_lights"] = positions is not None
    report(1.0, "done")
    return out


def _near_positions(lights: LightSet, dome_radius):
    """Light positions in pixels for a near-light solve, or None (distant lights)."""
    if dome_radius is not None:
        if not (np.isfinite(dome_radius) and dome_radius > 0):
            raise ValueError(f"dome_radius must be a positive number of pixels, got {dome_radius!r}")
        return float(dome_radius) * lights.directions
    return lights.positions


def rerender_residual(images, lights: LightSet | np.ndarray, image: RGBNImage, *,
                      dome_radius: float | None = None) -> np.ndarray:
    """Relative re-render residual of every flash image: how well the solved faces explain them.

    Parameters
    ----------
    images : (N, H, W, 3) float array
        The linear flash images that were solved (before division by the light intensities).
    lights : LightSet or (N, 3) array
        Their lights (as given to :func:`handheld_rgbn`).
    image : RGBNImage
        The solved normals, RGB albedo and mask.
    dome_radius : float, optional
        Near lights on a dome of this radius in pixels (as given to :func:`handheld_rgbn`);
        ``lights.positions`` (near lights) are used otherwise, if given.

    Returns
    -------
    (N,) float64
        ``Σ |I − ρ e max(0, l·n) f| / Σ I`` over the mask's pixels and the three channels, per
        image (e the light's intensity, f the near lights' fall-off, 1 for distant lights).
    """
    if not isinstance(lights, LightSet):
        lights = LightSet(np.asarray(lights, dtype=np.float64))
    imgs = np.asarray(images, np.float32)
    idx = np.flatnonzero(image.mask)
    if idx.size == 0:
        raise ValueError("image has an empty mask: nothing to re-render")
    n = len(imgs)
    e = np.ones((n, 3)) if lights.intensities is None else lights.intensities
    normals = image.normals.reshape(-1, 3)[idx]
    albedo = image.albedo.reshape(-1, 3)[idx]
    flat = imgs.reshape(n, -1, 3)
    out = np.zeros(n)
    positions = _near_positions(lights, dome_radius)
    for start in range(0, idx.size, 1 << 15):
        sl = slice(start, start + (1 << 15))
        if positions is None:
            shade = np.clip(normals[sl] @ lights.directions.T.astype(np.float32), 0, None).T  # (N, P)
        else:
            from common.acquisition.photometric import point_light_field
            d, f = point_light_field(positions, image.mask.shape, idx[sl])
            shade = (np.clip(np.einsum("pk,pnk->pn", normals[sl], d), 0, None) * f).T
        pred = shade[..., None] * albedo[sl][None] * e[:, None, :].astype(np.float32)
        measured = flat[:, idx[sl]]
        out += np.abs(measured - pred).sum(axis=(1, 2))
    total = flat[:, idx].sum(axis=(1, 2))
    return out / np.maximum(total, 1e-12)


#: Dome radii tried by :func:`estimate_dome_radius`, in frame widths (the larger side).
DOME_RADII = (1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 12.0)


def estimate_dome_radius(images, lights: LightSet | np.ndarray, *, mask=None, saturated=None,
                         radii=DOME_RADII, min_gain: float = 0.005, max_pixels: int = 40000):
    """The dome radius whose near-light solve re-renders a capture best (or None: distant lights).

    Parameters
    ----------
    images : (N, H, W, 3) float array
        Linear flash images.
    lights : LightSet or (N, 3) array
        Unit light directions from the dome's centre (the ``.lp`` file).
    mask, saturated : optional
        Object pixels, saturated measurements (as for :func:`handheld_rgbn`).
    radii : sequence of float
        Candidate radii in frame widths (the frame's larger side).
    min_gain : float
        A near-light radius is chosen only if it lowers the mean relative re-render residual by
        more than this share of the distant-light residual (else None).
    max_pixels : int
        The frame is subsampled to about this many pixels for the search.

    Returns
    -------
    radius : float or None
        Pixels of the full frame; None = distant lights fit as well.
    table : list of (radius or None, mean residual)
        Every candidate's mean re-render residual (least squares, :func:`rerender_residual`).

    Notes
    -----
    A least-squares solve per candidate on the subsampled frame; the radius assumes the dome is
    centred on the image centre and the object is near the plane z = 0.
    """
    if not isinstance(lights, LightSet):
        lights = LightSet(np.asarray(lights, dtype=np.float64))
    imgs = np.asarray(images, np.float32)
    n, h, w = imgs.shape[:3]
    step = max(1, int(round(np.sqrt(h * w / max_pixels))))
    sub = imgs[:, ::step, ::step]
    m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    m = m[::step, ::step]
    sat = None if saturated is None else np.asarray(saturated, bool)[:, ::step, ::step]
    table = []
    for k in (None, *radii):
        r_sub = None if k is None else k * max(h, w) / step
        solved = handheld_rgbn(sub, lights, mask=m, saturated=sat, method="least_squares", discontinuities=False,
                               dome_radius=r_sub)
        table.append((None if k is None else k * max(h, w),
                      float(rerender_residual(sub, lights, solved, dome_radius=r_sub).mean())))
    far = table[0][1]
    best = min(table, key=lambda t: t[1])
    radius = best[0] if best[1] < far * (1.0 - min_gain) else None
    return radius, table


def normal_tilt_gradient(image: RGBNImage) -> tuple[float, float]:
    """The slow tilt of the normals across the frame, in degrees per frame width and height.

    Fits ``n_x ≈ a + b·x`` and ``n_y ≈ c + d·y`` (x, y in frame widths/heights from the centre)
    over the mask by least squares; returns ``(degrees(b), degrees(d))`` — for a flat object under
    distant lights that really were near, the normals swing outwards across the frame
    (b, d > 0 when the lights are nearer than assumed).
    """
    h, w = image.mask.shape
    rows, cols = np.nonzero(image.mask)
    if rows.size < 3:
        raise ValueError("image has fewer than 3 masked pixels")
    x = cols / max(w - 1, 1) - 0.5
    y = 0.5 - rows / max(h - 1, 1)
    n = image.normals[rows, cols]
    slope_x = np.polyfit(x, np.arcsin(np.clip(n[:, 0], -1, 1)), 1)[0]
    slope_y = np.polyfit(y, np.arcsin(np.clip(n[:, 1], -1, 1)), 1)[0]
    return float(np.degrees(slope_x)), float(np.degrees(slope_y))


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
