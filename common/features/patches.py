"""Patch sampling along the contour, in millimetres (§5.2.1).

Circular patches 10 mm wide every 5 mm of arc, centred 8 mm inward from the contour along the
inward normal, and 20 mm variants centred 13 mm inward (so both keep a 3 mm margin from the edge).
A patch that falls partly off the fragment is not averaged over the background: its *coverage*
(fraction of the disc area on the fragment) is recorded, and below ``min_coverage`` its values are
missing (NaN) in the feature table.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.features.contour import Contour

#: (kind, diameter_mm, inset_mm) of the patch variants of §5.2.1
PATCH_KINDS = (("p10", 10.0, 8.0), ("p20", 20.0, 13.0))
#: arc spacing of patch centres, mm
PATCH_SPACING_MM = 5.0
#: patches with less of their disc on the fragment than this get missing values
MIN_COVERAGE = 0.6


@dataclass
class PatchSet:
    """Patches of one fragment face (fragment frame, mm).

    Attributes
    ----------
    centers_mm : (N, 2) patch centres (x right, y down)
    normals : (N, 2) outward contour normal at the patch's contour point
    arc_mm : (N,) arc position of the patch's contour point
    contour_mm : (N, 2) the contour point the patch belongs to
    kind : (N,) str, 'p10' or 'p20'
    diameter_mm : (N,) float
    coverage : (N,) fraction of the patch disc that lies on the fragment
    """

    centers_mm: np.ndarray
    normals: np.ndarray
    arc_mm: np.ndarray
    contour_mm: np.ndarray
    kind: np.ndarray
    diameter_mm: np.ndarray
    coverage: np.ndarray

    def __len__(self) -> int:
        return len(self.arc_mm)


def disk_window(center_xy_mm, radius_mm, pixel_mm, shape):
    """Anti-aliased disc weights around a sub-pixel centre, cropped to an image.

    Returns ``(rows, cols, weights, full_area_px)``: slices into an (H, W) array, the weights of
    the cropped window (pixel coverage of the disc, 0..1) and the area of the whole disc in
    pixels (so coverage of a disc that runs off the image counts the missing part as off-fragment).
    """
    cx, cy = center_xy_mm[0] / pixel_mm, center_xy_mm[1] / pixel_mm
    r = radius_mm / pixel_mm
    r0, r1 = int(np.floor(cy - r - 1)), int(np.ceil(cy + r + 2))
    c0, c1 = int(np.floor(cx - r - 1)), int(np.ceil(cx + r + 2))
    full_area = np.pi * r * r
    rr0, rr1 = max(r0, 0), min(r1, shape[0])
    cc0, cc1 = max(c0, 0), min(c1, shape[1])
    if rr0 >= rr1 or cc0 >= cc1:
        return slice(0, 0), slice(0, 0), np.zeros((0, 0), np.float32), full_area
    yy = np.arange(rr0, rr1, dtype=np.float32)[:, None] - cy
    xx = np.arange(cc0, cc1, dtype=np.float32)[None, :] - cx
    w = np.clip(r + 0.5 - np.sqrt(yy * yy + xx * xx), 0.0, 1.0)
    return slice(rr0, rr1), slice(cc0, cc1), w, full_area


def sample_patches(contour: Contour, coverage_map, pixel_mm, *, spacing_mm=PATCH_SPACING_MM,
                   kinds=PATCH_KINDS) -> PatchSet:
    """Place circular patches along a fragment contour (§5.2.1).

    Parameters
    ----------
    contour : Contour
        Outline from :func:`~common.features.contour.fragment_contour`.
    coverage_map : (H, W) float
        Fraction of each pixel on the fragment (a boolean mask works too), on the pixel grid of
        ``pixel_mm``.
    pixel_mm : float
        Pixel size of ``coverage_map`` in mm.
    spacing_mm : float
        Arc spacing between consecutive patch positions, mm (5 mm in the thesis).
    kinds : sequence of (kind, diameter_mm, inset_mm)
        Patch variants; the default is 10 mm patches 8 mm inward and 20 mm patches 13 mm inward.

    Returns
    -------
    PatchSet
        One patch per variant and arc position, with its coverage.

    References
    ----------
    Toler-Franklin 2011, §5.2.1 ("patches 10 mm wide every 5 mm along the contour, 8 mm in").
    """
    if not spacing_mm > 0:
        raise ValueError(f"spacing_mm must be positive, got {spacing_mm}")
    cov = np.asarray(coverage_map, dtype=np.float32)
    if cov.ndim != 2:
        raise ValueError(f"coverage_map must be 2-D, got shape {cov.shape}")
    n_pos = max(1, int(np.floor(contour.length_mm / spacing_mm)))
    arc = np.arange(n_pos) * spacing_mm
    pts, nrm = contour.at(arc)
    out = {k: [] for k in ("centers_mm", "normals", "arc_mm", "contour_mm", "kind", "diameter_mm", "coverage")}
    for kind, diameter, inset in kinds:
        centres = pts - inset * nrm
        for i in range(n_pos):
            rows, cols, w, full = disk_window(centres[i], diameter / 2, pixel_mm, cov.shape)
            c = float(np.sum(w * cov[rows, cols]) / full) if full > 0 else 0.0
            out["centers_mm"].append(centres[i])
            out["normals"].append(nrm[i])
            out["arc_mm"].append(arc[i])
            out["contour_mm"].append(pts[i])
            out["kind"].append(kind)
            out["diameter_mm"].append(diameter)
            out["coverage"].append(min(c, 1.0))
    return PatchSet(
        centers_mm=np.asarray(out["centers_mm"], float).reshape(-1, 2),
        normals=np.asarray(out["normals"], float).reshape(-1, 2),
        arc_mm=np.asarray(out["arc_mm"], float),
        contour_mm=np.asarray(out["contour_mm"], float).reshape(-1, 2),
        kind=np.asarray(out["kind"], dtype="U8"),
        diameter_mm=np.asarray(out["diameter_mm"], float),
        coverage=np.asarray(out["coverage"], float),
    )
