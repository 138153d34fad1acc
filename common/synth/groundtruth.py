"""The ground-truth file of a wall: schema ``tessera.groundtruth``.

Layout (HDF5, written through :meth:`common.store.Store.write`)::

    attrs: wall_id, width_mm, height_mm, dpi, n_missing, params (JSON)
    fragments/ids            (N,) str     fragment ids
    fragments/pose           (N, 3) f8    angle_deg, tx_mm, ty_mm (NaN for spurious)
    fragments/spurious       (N,) bool
    fragments/area_mm2       (N,) f8
    fragments/notes          (N,) str     JSON: fading / discolouration applied
    fragments/contours/<id>  (M, 2) f8    outer contour, fragment frame mm (x right, y down)
    adjacency/a, adjacency/b (P,) str     neighbour pairs, a < b
    adjacency/shared_mm      (P,) f8      crack length shared before erosion
    correspondences/<a>|<b>/a, .../b  (K, 2) f8  corresponding contour points, each in its frame
    preview/albedo, preview/labels, preview/label_ids   (optional) the wall at ~1 mm/px

Fragment images are not in this file: they are the fragments' own RGBN or scans artifacts.
"""

from __future__ import annotations

import json
from typing import Mapping

import h5py
import numpy as np

from common.store import ArtifactError, ArtifactRef, Store
from common.synth.wall import Fragment, Wall

SCHEMA = "tessera.groundtruth"
SCHEMA_VERSION = 1
_STR = h5py.string_dtype()


def write_groundtruth(f: h5py.Group, wall: Wall, *, preview: bool = True) -> None:
    """Write a wall's ground truth into an open HDF5 file or group."""
    f.attrs["wall_id"] = wall.id
    f.attrs["width_mm"] = float(wall.width_mm)
    f.attrs["height_mm"] = float(wall.height_mm)
    f.attrs["dpi"] = float(wall.dpi)
    f.attrs["n_missing"] = int(wall.n_missing)
    f.attrs["params"] = json.dumps(wall.params, sort_keys=True, default=str)
    g = f.create_group("fragments")
    g.create_dataset("ids", data=np.array([fr.id for fr in wall.fragments], dtype=object), dtype=_STR)
    g.create_dataset("pose", data=np.array([fr.pose if fr.pose is not None else (np.nan,) * 3
                                            for fr in wall.fragments], float).reshape(-1, 3))
    g.create_dataset("spurious", data=np.array([fr.spurious for fr in wall.fragments], bool))
    g.create_dataset("area_mm2", data=np.array([fr.area_mm2 for fr in wall.fragments], float))
    g.create_dataset("notes", data=np.array([json.dumps(fr.notes, sort_keys=True) for fr in wall.fragments],
                                            dtype=object), dtype=_STR)
    cg = g.create_group("contours")
    for fr in wall.fragments:
        if fr.contour_mm is not None:
            cg.create_dataset(fr.id, data=np.asarray(fr.contour_mm, float), compression="gzip", compression_opts=1)
    a = f.create_group("adjacency")
    a.create_dataset("a", data=np.array([p[0] for p in wall.adjacency], dtype=object), dtype=_STR)
    a.create_dataset("b", data=np.array([p[1] for p in wall.adjacency], dtype=object), dtype=_STR)
    a.create_dataset("shared_mm", data=np.array([p[2] for p in wall.adjacency], float))
    c = f.create_group("correspondences")
    for (ia, ib), (pa, pb) in wall.correspondences.items():
        pg = c.create_group(f"{ia}|{ib}")
        pg.create_dataset("a", data=np.asarray(pa, float).reshape(-1, 2))
        pg.create_dataset("b", data=np.asarray(pb, float).reshape(-1, 2))
    if preview and wall.preview:
        p = f.create_group("preview")
        p.attrs["grid_mm"] = float(wall.preview.get("grid_mm", 1.0))
        albedo8 = np.clip(np.asarray(wall.preview["albedo"]) * 255 + 0.5, 0, 255).astype(np.uint8)
        p.create_dataset("albedo", data=albedo8,
                         compression="gzip", compression_opts=4)
        if "labels" in wall.preview:
            p.create_dataset("labels", data=np.asarray(wall.preview["labels"], np.int32), compression="gzip",
                             compression_opts=4)
            p.create_dataset("label_ids", data=np.array(wall.preview["label_ids"], dtype=object), dtype=_STR)


def read_groundtruth(f: h5py.Group) -> Wall:
    """Read a wall written by :func:`write_groundtruth` (fragments without images)."""
    try:
        g = f["fragments"]
        ids = [s.decode() if isinstance(s, bytes) else str(s) for s in g["ids"][()]]
        poses, spur, area = g["pose"][()], g["spurious"][()], g["area_mm2"][()]
        notes = [json.loads(s.decode() if isinstance(s, bytes) else s) for s in g["notes"][()]] \
            if "notes" in g else [{} for _ in ids]
        frags = []
        for i, fid in enumerate(ids):
            pose = None if np.isnan(poses[i]).any() else tuple(float(v) for v in poses[i])
            cont = g["contours"][fid][()] if fid in g["contours"] else None
            frags.append(Fragment(fid, pose=pose, spurious=bool(spur[i]), area_mm2=float(area[i]), contour_mm=cont,
                                  notes=notes[i]))
        a = f["adjacency"]
        dec = lambda arr: [s.decode() if isinstance(s, bytes) else str(s) for s in arr]
        adjacency = [(x, y, float(l)) for x, y, l in zip(dec(a["a"][()]), dec(a["b"][()]), a["shared_mm"][()])]
        corr = {}
        for key, pg in f["correspondences"].items():
            ia, ib = key.split("|")
            corr[(ia, ib)] = (pg["a"][()], pg["b"][()])
        preview = {}
        if "preview" in f:
            p = f["preview"]
            preview = dict(albedo=p["albedo"][()].astype(np.float32) / 255.0, grid_mm=float(p.attrs["grid_mm"]))
            if "labels" in p:
                preview.update(labels=p["labels"][()], label_ids=dec(p["label_ids"][()]))
        return Wall(str(f.attrs["wall_id"]), frags, adjacency, corr, float(f.attrs["width_mm"]),
                    float(f.attrs["height_mm"]), float(f.attrs["dpi"]), n_missing=int(f.attrs["n_missing"]),
                    params=json.loads(f.attrs["params"]), preview=preview)
    except KeyError as exc:
        raise ArtifactError(f"ground truth in {f.file.filename} lacks {exc}") from exc


def save_groundtruth(store: Store, wall: Wall, relpath: str | None = None, *,
                     provenance: Mapping | None = None) -> ArtifactRef:
    """Store a wall's ground truth as an immutable artifact, by default ``groundtruth/<wall id>.h5``."""
    relpath = relpath or f"groundtruth/{wall.id}.h5"
    prov = {"generator": "common.synth", **wall.params, **(provenance or {})}
    return store.write(relpath, SCHEMA, SCHEMA_VERSION, lambda f: write_groundtruth(f, wall), provenance=prov)


def load_groundtruth(store: Store, ref: ArtifactRef | Mapping | str) -> Wall:
    """Load (and digest-check, given a pointer) a ``tessera.groundtruth`` artifact."""
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        return read_groundtruth(f)


def label_patch_pairs(wall: Wall, id_a: str, points_a_mm: np.ndarray, id_b: str, points_b_mm: np.ndarray, *,
                      tol_mm: float = 5.0, reach_mm: float = 12.0) -> np.ndarray:
    """Ground-truth labels for patch pairs of two fragments: which patches face each other across a join.

    A patch of A and a patch of B match when the fragments are true neighbours, each patch lies
    within ``reach_mm`` of the shared crack (of its own fragment's corresponding contour points),
    and their projections onto the crack lie within ``tol_mm`` of each other on the wall (a crack
    point's wall position is the midpoint of its two corresponding contour points). Symmetric in
    A and B.

    Parameters
    ----------
    wall : Wall
    id_a, id_b : str
        Fragment ids.
    points_a_mm, points_b_mm : (Na, 2), (Nb, 2) arrays
        Patch positions (e.g. centres or contour anchors) in each fragment's own frame, mm
        (x right, y down), as in the feature table.
    tol_mm : float
        How far apart along the crack two patches may be and still match.
    reach_mm : float
        How far from the crack a patch centre may be (patches sit ~8 mm inward, §5.4).

    Returns
    -------
    (Na, Nb) bool
        True for a true match; all False for fragments that are not neighbours.
    """
    pa_pts = np.asarray(points_a_mm, float).reshape(-1, 2)
    pb_pts = np.asarray(points_b_mm, float).reshape(-1, 2)
    out = np.zeros((len(pa_pts), len(pb_pts)), bool)
    if tol_mm <= 0 or reach_mm <= 0:
        raise ValueError("tol_mm and reach_mm must be positive")
    key, swap = ((id_a, id_b), False) if id_a < id_b else ((id_b, id_a), True)
    if key not in wall.correspondences or not len(pa_pts) or not len(pb_pts):
        return out
    ca, cb = wall.correspondences[key]
    if swap:
        ca, cb = cb, ca
    if not len(ca):
        return out
    from scipy.spatial import cKDTree
    da, ia = cKDTree(ca).query(pa_pts)
    db, ib = cKDTree(cb).query(pb_pts)
    fa, fb = wall.fragment(id_a), wall.fragment(id_b)
    crack = 0.5 * (fa.to_wall(ca) + fb.to_wall(cb))     # wall position of each crack sample
    qa, qb = crack[ia], crack[ib]                       # each patch projected onto the crack
    near = np.hypot(*(qa[:, None, :] - qb[None, :, :]).transpose(2, 0, 1)) <= tol_mm
    return near & (da <= reach_mm)[:, None] & (db <= reach_mm)[None, :]
