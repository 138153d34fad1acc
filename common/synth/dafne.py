"""Import of fragment sets with ground-truth placement: the DAFNE format.

DAFNE (Dataset of Fresco Fragments for Digital Reconstruction) gives, per fresco, RGBA fragment
images ``fragments/frag_eroded_<i>.png``, a placement file ``fragments.txt`` (``index x y angle``:
the fragment image's centre in fresco pixels, and an angle in degrees applied with OpenCV
``getRotationMatrix2D(centre, angle, 1)`` -- counter-clockwise on screen, canvas size kept -- before
pasting with the alpha mask) and ``fragments_s.txt``, the spurious fragments that belong nowhere.
Neighbours are fragments whose placed masks come within ``neighbour_px`` pixels of each other.

Colour only (no normals, no height). DAFNE has no physical scale: a nominal ``dpi`` is assumed
(default 50 dpi, 0.508 mm per pixel, which makes the fragments a few centimetres across like
real fresco fragments); every mm figure of the imported wall follows from it.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

from common.imports.fragments import fragment_from_image
from common.rgbn.io import srgb_to_linear
from common.synth.stats import read_fragment_rgba
from common.synth.wall import Fragment, Wall

# a boundary at a random angle has max(|cos|, |sin|) contour pixels per pixel of length: mean 2 sqrt(2) / pi
_BOUNDARY_PX_PER_LENGTH = 2 * np.sqrt(2) / np.pi


def _read_table(path: Path) -> list[list[str]]:
    rows = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if parts and not parts[0].startswith("#"):
            rows.append(parts)
    return rows


def import_dafne(path: str | os.PathLike, *, dpi: float = 50.0, neighbour_px: float = 6.0,
                 wall_id: str | None = None, load_images: bool = True) -> Wall:
    """Read a DAFNE fragment set into the :class:`~common.synth.wall.Wall` ground-truth form.

    Parameters
    ----------
    path : path
        Directory with ``fragments/``, ``fragments.txt`` and ``fragments_s.txt`` (and optionally
        ``fresco.jpg``, used only for the preview).
    dpi : float
        Nominal sampling (DAFNE has no physical scale); 50 dpi = 0.508 mm per pixel.
    neighbour_px : float
        Placed masks closer than this (fresco pixels) make two fragments neighbours.
    wall_id : str, optional
        Id of the wall (default: the directory name, prefixed ``dafne-`` if it lacks it); fragment ids are
        ``<wall id>-<index>``.
    load_images : bool
        Keep each fragment's RGBN image (colour only).

    Returns
    -------
    Wall
        Placed fragments carry their pose (fragment frame mm -> fresco mm, ``wall = R p + t``);
        spurious ones have ``pose=None``. ``adjacency`` and ``correspondences`` as for a
        synthetic wall.

    References
    ----------
    M. Dondi, L. Lombardi, M. Malagodi, M. Licchelli, "DAFNE: a dataset of fresco fragments for
    digital anastlylosis", Pattern Recognition Letters 138, 2020.
    """
    root = Path(path)
    if not (root / "fragments.txt").is_file() or not (root / "fragments").is_dir():
        raise ValueError(f"path {root} is not a DAFNE set: it needs fragments.txt and fragments/")
    if not dpi > 0:
        raise ValueError(f"dpi must be positive, got {dpi}")
    if neighbour_px < 0:
        raise ValueError(f"neighbour_px must be >= 0, got {neighbour_px}")
    pm = 25.4 / dpi
    wall_id = wall_id or (root.name if root.name.lower().startswith("dafne") else f"dafne-{root.name}")
    placements = {int(r[0]): (float(r[1]), float(r[2]), float(r[3])) for r in _read_table(root / "fragments.txt")}
    spurious = set()
    if (root / "fragments_s.txt").is_file():
        spurious = {int(r[0]) for r in _read_table(root / "fragments_s.txt")}
    indices = sorted(set(placements) | spurious)

    frags: list[Fragment] = []
    placed: dict[str, tuple] = {}   # id -> (window x0, y0, placed mask, contour in fresco px)
    for i in indices:
        img = read_fragment_rgba(root / "fragments" / f"frag_eroded_{i}.png")
        h, w = img.shape[:2]
        mask = img[..., 3] > 127      # the fragment proper (RGBN mask, contour)
        footprint = img[..., 3] > 0   # what pasting with the alpha mask covers (neighbour test)
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cont_px = max(contours, key=len).reshape(-1, 2).astype(np.float64) if contours else np.zeros((0, 2))
        fid = f"{wall_id}-{i}"
        rgbn = None
        if load_images:  # the importers' cut-out path: mask alpha > 50 %, albedo linear from sRGB
            rgbn = fragment_from_image(img, dpi=dpi, background="alpha")
            rgbn.attrs = {"source": "DAFNE", "face": "front"}
        pose = None
        if i in placements and i not in spurious:
            x, y, ang = placements[i]
            # getRotationMatrix2D(c, ang) has linear part R(-ang) in our (x right, y down) frame
            a = np.deg2rad(-ang)
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            c = np.array([w / 2.0, h / 2.0])
            t_px = np.array([x, y]) - R @ c
            pose = (float(-ang), float(t_px[0] * pm), float(t_px[1] * pm))
            # placed mask in a window of the fresco
            x0, y0 = int(np.floor(x - w / 2.0)), int(np.floor(y - h / 2.0))
            M = np.hstack([R, (t_px - (x0, y0))[:, None]])
            pm_mask = cv2.warpAffine(footprint.astype(np.uint8), M, (w, h), flags=cv2.INTER_NEAREST) > 0
            placed[fid] = (x0, y0, pm_mask, cont_px @ R.T + t_px)
        frags.append(Fragment(fid, rgbn=rgbn, surface=None, pose=pose, spurious=pose is None,
                              area_mm2=float(mask.sum() * pm * pm), contour_mm=cont_px * pm))

    adjacency, corr = _neighbours(frags, placed, neighbour_px, pm)
    preview = {}
    fresco = root / "fresco.jpg"
    width = max((x0 + m.shape[1] for x0, _, m, _ in placed.values()), default=0)
    height = max((y0 + m.shape[0] for _, y0, m, _ in placed.values()), default=0)
    if fresco.is_file():
        img = cv2.imread(str(fresco), cv2.IMREAD_COLOR)
        if img is not None:
            preview = dict(albedo=srgb_to_linear(img[..., ::-1] / np.float32(255)), grid_mm=pm)
            height, width = img.shape[:2]
    return Wall(wall_id, frags, adjacency, corr, width * pm, height * pm, float(dpi), n_missing=0,
                params={"source": "DAFNE", "path": str(root), "dpi": dpi, "neighbour_px": neighbour_px},
                preview=preview)


def _neighbours(frags, placed, neighbour_px, pm):
    """Pairs of placed fragments whose masks come within ``neighbour_px``; shared length, correspondences."""
    ids = sorted(placed)
    r = int(np.ceil(neighbour_px)) + 1
    boxes = {k: (x0, y0, x0 + m.shape[1], y0 + m.shape[0]) for k, (x0, y0, m, _) in placed.items()}
    trees = {k: cKDTree(v[3]) for k, v in placed.items() if len(v[3])}
    adjacency, corr = [], {}
    for ai, a in enumerate(ids):
        xa0, ya0, ma, ca = placed[a]
        ax0, ay0, ax1, ay1 = boxes[a]
        # distance to A's placed mask, on A's window grown by r
        pad = np.pad(~ma, r, constant_values=True).astype(np.uint8)
        dist_a = cv2.distanceTransform(pad, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        for b in ids[ai + 1:]:
            bx0, by0, bx1, by1 = boxes[b]
            if bx0 > ax1 + r or bx1 < ax0 - r or by0 > ay1 + r or by1 < ay0 - r:
                continue
            xb0, yb0, mb, cb = placed[b]
            yy, xx = np.nonzero(mb)
            # B's pixels in A's padded window
            u, v = xx + xb0 - xa0 + r, yy + yb0 - ya0 + r
            ok = (u >= 0) & (v >= 0) & (u < dist_a.shape[1]) & (v < dist_a.shape[0])
            if not ok.any() or dist_a[v[ok], u[ok]].min() > neighbour_px:
                continue
            # contour points of each within the neighbour distance of the other
            da, ib = trees[b].query(ca) if b in trees else (np.full(len(ca), np.inf), None)
            db, _ = trees[a].query(cb) if a in trees else (np.full(len(cb), np.inf), None)
            # contours are of the solid (alpha > 127) fragments: allow for the soft alpha rim
            near_a = da <= neighbour_px + 2
            length_px = 0.5 * (near_a.sum() + (db <= neighbour_px + 2).sum()) / _BOUNDARY_PX_PER_LENGTH
            fa = next(f for f in frags if f.id == a)
            fb = next(f for f in frags if f.id == b)
            pa = fa.contour_mm[near_a]
            pb = fb.contour_mm[ib[near_a]] if ib is not None else np.zeros((0, 2))
            adjacency.append((a, b, float(length_px * pm)) if a < b else (b, a, float(length_px * pm)))
            corr[(a, b) if a < b else (b, a)] = (pa, pb) if a < b else (pb, pa)
    adjacency.sort()
    return adjacency, corr
