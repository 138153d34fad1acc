"""Real fragment collections with known placement, read as ground truth for the matcher's evaluation.

A *collection* is laid out as ``../shared/data/repair-dev`` (RePAIR, Pompeii frescoes): one folder
per object with its fragment images and, where the placement is known, ``truth.csv``
(``rpf,x,y,rot``); folders without one hold distractors (the variations accepted:
:func:`common.synth.stats.read_collection`). :func:`collection_wall` imports every image
as a colour-only fragment (:func:`common.imports.fragments.fragment_from_image`) and turns the
placements into the :class:`~common.synth.wall.Wall` ground-truth form the evaluation uses; what it
leaves out (a damaged picture, an unusable ``truth.csv`` row or file, a picture of a placed object no row
places) is logged as a warning (logger ``tessera.collection``) and listed in ``params['skipped']``.

Neighbours follow ../shared/data/README.md: two pieces of one object whose placed outlines come
within ``near_px`` (48) canvas pixels of each other along at least ``min_run_px`` (100) pixels
(:func:`common.synth.stats.neighbour_gaps`). True neighbours need not touch: real cracks lose
material, and the placed outlines of RePAIR's neighbours run 1–8 mm apart.
"""

from __future__ import annotations

import logging
import os

import numpy as np

from common.synth.wall import Fragment, Wall

log = logging.getLogger("tessera.collection")


def piece_pose(matrix: np.ndarray, pixel_mm: float) -> tuple[float, float, float]:
    """Pose ``(angle_deg, tx_mm, ty_mm)`` of a placed piece from its crop-pixel → canvas-pixel matrix.

    The fragment frame is crop pixel × ``pixel_mm`` (x right, y down) and the wall frame canvas
    pixel × ``pixel_mm``, so ``wall = R(angle) p + t`` with ``R = [[cos, −sin], [sin, cos]]``.
    OpenCV's ``getRotationMatrix2D(centre, rot, 1)`` (counter-clockwise on screen) has linear part
    ``R(−rot)`` in this frame.
    """
    m = np.asarray(matrix, float)
    if m.shape != (2, 3):
        raise ValueError(f"matrix must be (2, 3), got {m.shape}")
    angle = float(np.degrees(np.arctan2(m[1, 0], m[0, 0])))
    return angle, float(m[0, 2] * pixel_mm), float(m[1, 2] * pixel_mm)


def collection_wall(path: str | os.PathLike, *, dpi: float = 150.0, near_px: float = 48.0,
                    min_run_px: float = 100.0, progress=None, strict: bool = False) -> Wall:
    """Read a placed collection of fragment images into the :class:`Wall` ground-truth form.

    Parameters
    ----------
    path : path
        Collection directory (one folder per object, RGBA PNGs, ``truth.csv`` where placed).
    dpi : float
        Nominal sampling of the images (RePAIR's files carry none; 150 dpi = 0.169 mm per pixel,
        RePAIR's own evaluation uses 187 dpi). Every mm figure follows from it.
    near_px, min_run_px : float
        Neighbour definition in canvas pixels (see the module docstring).
    progress : callable(fraction, text), optional
    strict : bool
        Refuse a damaged picture or an unusable ``truth.csv`` row or file (ValueError naming every
        damaged picture, or the file and line) instead of leaving it out and going on
        (:func:`~common.synth.stats.read_collection` with or without ``skipped``).

    Returns
    -------
    Wall
        One fragment per image (id = file stem; ``notes['object']`` its folder), placed fragments
        with their pose in their object's frame (objects are separate frames: only pairs within
        one object are ever neighbours), distractors with ``pose=None`` and ``spurious=True``;
        ``adjacency`` = ``(a, b, shared crack mm)``; ``params['skipped']`` what was left out and why.
        A picture of an object whose ``truth.csv`` places others but not it is left out: its place is
        unknown, and as a distractor of its own object its true joins would count as wrong matches.
        The pictures of an object no row places (no ``truth.csv``, or one without rows) are distractors.
    """
    from common.imports.fragments import fragment_from_image
    from common.synth.stats import neighbour_gaps, read_collection

    if not (np.isfinite(dpi) and dpi > 0):
        raise ValueError(f"dpi must be positive, got {dpi}")
    skipped: list = []
    pieces = read_collection(path, skipped=None if strict else skipped)
    placed_objects = {p.object for p in pieces if p.matrix is not None}
    kept = []
    for p in pieces:
        if p.matrix is None and p.object in placed_objects:
            message = (f"{p.file or p.object + '/' + p.id}: no row of its folder's truth.csv places it (none names "
                       "it, or the one that does is unusable), so its place is unknown: left out (as a distractor of "
                       "its own object its true joins would count as wrong)")
            log.warning(message)
            skipped.append(message)
        else:
            kept.append(p)
    pieces = kept
    pm = 25.4 / dpi
    ids = [p.id for p in pieces]
    if len(set(ids)) != len(ids):  # the same file name in two objects: qualify by object
        ids = [f"{p.object}-{p.id}" for p in pieces]
    frags, imported = [], []
    for i, (fid, p) in enumerate(zip(ids, pieces)):
        try:
            rgbn = fragment_from_image(p.rgba, dpi=dpi, background="alpha")
        except ValueError as exc:     # a piece the import cannot use: named, and left out unless strict
            message = f"{p.file or p.object + '/' + p.id}: cannot be imported as a fragment ({exc})"
            if strict:
                raise ValueError(message) from None
            log.warning(message + ": left out")
            skipped.append(message + ": left out")
            continue
        imported.append(p)
        rgbn.attrs.update({"source": "collection", "object": p.object, "face": "front"})
        pose = piece_pose(p.matrix, pm) if p.matrix is not None else None
        frags.append(Fragment(fid, rgbn=rgbn, pose=pose, spurious=pose is None,
                              area_mm2=float(rgbn.mask.sum() * pm * pm), notes={"object": p.object}))
        if progress:
            progress((i + 1) / len(pieces), f"imported {fid}")
    by_key = {(p.object, p.id): fid for fid, p in zip(ids, pieces)}
    adjacency = [(by_key[(g["object"], g["a"])], by_key[(g["object"], g["b"])], g["run_px"] * pm)
                 for g in neighbour_gaps(imported, near_px=near_px, min_run_px=min_run_px)]
    return Wall(f"collection-{os.path.basename(os.path.normpath(str(path)))}", frags, adjacency, {}, 0.0, 0.0,
                float(dpi), params={"source": "collection", "path": str(path), "dpi": dpi, "near_px": near_px,
                                    "min_run_px": min_run_px, "skipped": skipped})


def relative_pose_error(pose_a, pose_b, proposed, centre_b_mm) -> tuple[float, float]:
    """Angle (degrees) and displacement (mm, at ``centre_b_mm``) between a proposed relative pose of
    B in A's frame and the one the two fragments' ground-truth poses give.

    ``pose_a``, ``pose_b`` map each fragment's frame into the wall's; ``proposed`` is
    ``(angle_deg, tx_mm, ty_mm)`` mapping B's frame into A's (:class:`~common.matching.alignment.Alignment`).
    """
    from common.matching.alignment import pose_matrix

    truth = np.linalg.inv(pose_matrix(*pose_a)) @ pose_matrix(*pose_b)
    prop = pose_matrix(*proposed)
    d_angle = np.degrees(np.arctan2(prop[1, 0], prop[0, 0]) - np.arctan2(truth[1, 0], truth[0, 0]))
    c = np.array([centre_b_mm[0], centre_b_mm[1], 1.0])
    return float(abs((d_angle + 180) % 360 - 180)), float(np.hypot(*((prop - truth) @ c)[:2]))


def within_object_recall(rankings: dict, neighbours: dict, ks=(1, 3)) -> dict:
    """Hit rate of a fragment's true neighbours among its top-k, ranked within its own object.

    Parameters
    ----------
    rankings : dict fragment → list of the other fragments of its object, best first
    neighbours : dict fragment → set of its true neighbours
    ks : k values

    Returns
    -------
    dict with ``recall`` {k: share of fragments (with ≥ 1 neighbour) that have a true neighbour in
    their top k}, ``random`` {k: the same expected for a random order}, ``incidence`` {k: share of
    (fragment, neighbour) links found in the top k}, ``hits`` {k: per fragment counted, 1 when a
    true neighbour is in its top k, else 0 (for :func:`~common.matching.evaluation.bootstrap_interval`)}
    and ``n`` (fragments counted); definitions as in ../shared/data/README.md.
    """
    from math import comb

    frags = [f for f in rankings if neighbours.get(f)]
    out = {"recall": {}, "random": {}, "incidence": {}, "hits": {}, "n": len(frags)}
    for k in ks:
        hit = inc = links = 0
        rnd = 0.0
        out["hits"][int(k)] = [int(bool(set(rankings[f][:k]) & neighbours[f])) for f in frags]
        for f in frags:
            top = set(rankings[f][:k])
            nb = neighbours[f]
            hit += bool(top & nb)
            inc += len(top & nb)
            links += len(nb)
            n, m = len(rankings[f]), len(nb)
            kk = min(k, n)
            # P(at least one neighbour among k drawn of n without replacement)
            rnd += 1.0 - (comb(n - m, kk) / comb(n, kk) if n - m >= kk else 0.0)
        out["recall"][int(k)] = hit / len(frags) if frags else float("nan")
        out["random"][int(k)] = rnd / len(frags) if frags else float("nan")
        out["incidence"][int(k)] = inc / links if links else float("nan")
    return out
