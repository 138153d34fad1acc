"""Colour and thickness along a fragment's boundary: the strip a neighbour shares across the crack.

Two fragments that were one piece carry the same painting and the same plaster up to the crack:
painted bands, lines and colour fields run over it, and the plaster thickness is continuous. The
*boundary profile* samples that strip — at fixed arc-length steps along the contour and at fixed
depths inside it — so the matcher can compare two fragments' boundaries sample by sample (the 2-D
"ribbon" of thesis §5.2.1, with the paint and the thickness in place of the 3-D surface;
:mod:`common.matching.ribbon`).

Channels, per depth ``d`` (mm inside the contour, along the inward normal):

* ``sqrt_r@d``, ``sqrt_g@d``, ``sqrt_b@d`` — √albedo (a perceptually more even scale than linear
  albedo, so dark paint differences count about as much as light ones);
* ``std_r@d``, ``std_g@d``, ``std_b@d`` — albedo standardised per fragment and channel,
  ``(a − mean) / (std + 0.02) × 0.15``: unchanged by a per-channel affine change of the whole
  fragment, i.e. by fading towards the plaster white or a tint (burial soil, soot, lime crust), so
  a faded fragment still matches its unfaded neighbour (the factor 0.15 brings its spread to that
  of √albedo);
* ``thickness@d`` — plaster thickness in mm (NaN where the height map has no value, e.g. a sample
  that falls in a notch of the outline, and everywhere when the image has no height map).
"""

from __future__ import annotations

import cv2
import numpy as np

from common.features.contour import Contour
from common.rgbn._filters import normalized_blur

#: arc-length step of the profile samples, mm
BOUNDARY_STEP_MM = 1.0
#: sampling depths inside the contour, mm: past the eroded and worn rim (~0.6 mm on average),
#: and close enough to the crack that the paint there still continues on the neighbour
BOUNDARY_DEPTHS_MM = (0.8, 1.6)
#: the per-fragment standardisation: ``(a − mean) / (std + STD_FLOOR) × STD_SCALE``
STD_FLOOR, STD_SCALE = 0.02, 0.15
#: the colour is smoothed at this scale (Gaussian sigma, mm) before it is sampled: paint is structured at 0.5 mm
#: and more, a scanner's noise per pixel, and at 150 dpi a sample is one pixel. Without it, noise of 2 grey levels
#: moved RePAIR's within-object recall @1 0.625 -> 0.500 (docs/features.md, "The boundary's colour at paint scale")
BOUNDARY_SIGMA_MM = 0.15


def boundary_channel_names(depths_mm=BOUNDARY_DEPTHS_MM) -> list[str]:
    """Channel names of :func:`boundary_profile`, in column order (grouped by kind, then depth)."""
    out = []
    for kind in ("sqrt", "std"):
        out += [f"{kind}_{c}@{d:g}" for d in depths_mm for c in "rgb"]
    return out + [f"thickness@{d:g}" for d in depths_mm]


def boundary_profile(contour: Contour, albedo: np.ndarray, pixel_mm: float, *, weight: np.ndarray | None = None,
                     thickness_mm: np.ndarray | None = None, step_mm: float = BOUNDARY_STEP_MM,
                     depths_mm=BOUNDARY_DEPTHS_MM, sigma_mm: float = BOUNDARY_SIGMA_MM) -> tuple[np.ndarray, float]:
    """Sample colour and thickness along a fragment's contour at fixed depths inside it.

    Parameters
    ----------
    contour : Contour
        The fragment outline (:func:`~common.features.contour.fragment_contour`), traversed
        clockwise on screen (fragment on the right), in the frame of ``albedo`` (x = col ×
        pixel_mm, y = row × pixel_mm).
    albedo : (H, W, 3) float
        Linear RGB albedo of the fragment (values outside the fragment are not used when
        ``weight`` is given).
    pixel_mm : float
        Pixel size of ``albedo`` (and ``weight``, ``thickness_mm``), mm.
    weight : (H, W) float, optional
        Fragment coverage of each pixel (1 inside); the per-fragment colour statistics use the
        pixels with coverage > 0.5. Default: every pixel with non-zero albedo.
    thickness_mm : (H, W) float, optional
        Plaster thickness; None gives NaN thickness channels.
    step_mm : float
        Arc-length step; the actual step is ``length / round(length / step_mm)`` so the samples
        close the loop evenly.
    depths_mm : sequence of float
        Depths inside the contour, mm.
    sigma_mm : float
        The colour is smoothed over the fragment at this scale first (a normalised convolution,
        :func:`common.rgbn._filters.normalized_blur`), so a sample is the paint there, not one pixel's
        noise (0: sampled as it is).

    Returns
    -------
    profile : (K, C) float32
        Sample ``k`` at arc position ``k × step`` from the contour start, columns
        :func:`boundary_channel_names`.
    step : float
        The actual arc-length step, mm.

    References
    ----------
    Toler-Franklin 2011, §5.2.1 (the ribbon matcher compares the strips along two fragments'
    boundaries); this is its 2-D colour-and-thickness analogue.
    """
    a = np.asarray(albedo, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"albedo must be (H, W, 3), got shape {a.shape}")
    if not (np.isfinite(pixel_mm) and pixel_mm > 0):
        raise ValueError(f"pixel_mm must be a positive number, got {pixel_mm}")
    if not step_mm > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    if not len(depths_mm) or min(depths_mm) < 0:
        raise ValueError(f"depths_mm must be one or more non-negative depths, got {depths_mm}")
    k = max(3, int(round(contour.length_mm / step_mm)))
    step = contour.length_mm / k
    pts, normals = contour.at(np.arange(k) * step)
    inside = (np.asarray(weight) > 0.5) if weight is not None else (a.sum(axis=2) > 0)
    if not inside.any():
        raise ValueError("the fragment has no pixels: cannot sample its boundary")
    a = np.nan_to_num(a, nan=0.0, posinf=1.0, neginf=0.0)
    if sigma_mm > 0:   # over the fragment only: the edge keeps the fragment's colour
        cover = np.asarray(weight, np.float32) if weight is not None else inside.astype(np.float32)
        a, _ = normalized_blur(a, cover, sigma_mm / pixel_mm)
        a[cover <= 0] = 0.0
    mean, std = a[inside].mean(axis=0), a[inside].std(axis=0)
    kinds = [np.sqrt(np.clip(a, 0.0, None)), (a - mean) / (std + STD_FLOOR) * STD_SCALE]
    # NaN thickness (off the height map) stays NaN: the matcher skips those samples
    th = None if thickness_mm is None else np.asarray(thickness_mm, np.float32)
    cols = {"sqrt": [], "std": [], "thickness": []}
    for d in depths_mm:
        q = (pts - normals * d) / pixel_mm   # inward: against the outward normal
        mx, my = q[None, :, 0].astype(np.float32), q[None, :, 1].astype(np.float32)
        for name, img in zip(("sqrt", "std"), kinds):
            cols[name].append(cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0])
        cols["thickness"].append(np.full((k, 1), np.nan, np.float32) if th is None else
                                 cv2.remap(th, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)[0][:, None])
    profile = np.concatenate(cols["sqrt"] + cols["std"] + cols["thickness"], axis=1).astype(np.float32)
    return profile, float(step)
