"""Patch-pair correspondences and training sets from ground truth (thesis §5.2.2, §5.8).

A *patch pair* is a patch of fragment A and a patch of fragment B (the 10 mm patches of §5.2.1,
one every 5 mm of contour). Its correspondence row holds, per column:

* ``fragment.<name>`` — the fragment-level descriptor correspondence (same for every patch pair of
  the two fragments),
* ``patch.<name>`` — the patch-level descriptor correspondence (§5.2.2: |a − b|, |a + b| for signed
  curvature, wrapped difference for angles — :func:`common.features.registry.correspondence`),
* ``match.gap_10mm``, ``match.gap_20mm`` — the per-match cue: RMS residual (mm) of the best rigid fit
  of A's boundary strip (±5 / ±10 mm of arc around the patch) onto B's strip traversed backwards,
  a local version of the ribbon matcher's gap (:mod:`common.matching.alignment`).

Ground truth: patches of two true neighbours *match* when their contour points, mapped to the
wall by the fragments' poses, lie within ``max_dist_mm`` of each other and their outward normals
point against each other (they face each other across the shared break). Non-matches are sampled
from pairs of fragments that are not neighbours.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field

import numpy as np

from common.features.patches import MIN_COVERAGE
from common.features.registry import correspondence, fragment_descriptors, patch_descriptors
from common.matching.alignment import signed_area_mm2
from common.matching.classifiers import MATCH_COLUMNS

#: patch kind whose positions are paired (the 10 mm patches of §5.2.1)
PAIR_KIND = "p10"
#: strip half-lengths (mm) of the per-match columns, and samples per strip
_STRIPS = ((5.0, 11), (10.0, 21))


def correspondence_columns() -> list[str]:
    """Names of the correspondence columns, in row order."""
    return ([d.key for d in fragment_descriptors()] + [d.key for d in patch_descriptors()] + list(MATCH_COLUMNS))


@dataclass
class FragmentCues:
    """What the matcher keeps of one fragment face: descriptor values and boundary strips.

    Attributes
    ----------
    fragment : str
    values : (F,) fragment-level descriptor values, in :func:`fragment_descriptors` order
    patches : (N, P) patch descriptor values of the paired patches (kind ``p10``)
    arc_mm : (N,) arc position of each patch's contour point
    points_mm, normals : (N, 2) contour point and outward normal of each patch (fragment frame)
    strips : list of (N, W, 2) centred boundary strips around each patch, one per strip length,
        traversed in the fragment's positive orientation
    patch_index : (N,) row of each patch in the feature table's patch arrays
    """

    fragment: str
    values: np.ndarray
    patches: np.ndarray
    arc_mm: np.ndarray
    points_mm: np.ndarray
    normals: np.ndarray
    strips: list = field(default_factory=list)
    patch_index: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.arc_mm)


def fragment_cues(table, fragment: str | None = None, *, kind: str = PAIR_KIND,
                  min_coverage: float = MIN_COVERAGE) -> FragmentCues:
    """Extract the matcher's view of a :class:`~common.features.table.FeatureTable`.

    Parameters
    ----------
    table : FeatureTable
        ``values`` (dict name → float), ``patch_values`` (N, P) in :func:`patch_descriptors`
        order (or named by ``patch_names``), ``patch_arc_mm``, ``patch_kind``, ``contour_mm``.
    fragment : str, optional
        Fragment id (default ``table.fragment`` if the table has one).
    kind : str
        Patch kind to pair.
    min_coverage : float
        Patches with less of their disc on the fragment are left out (their values are missing).
    """
    fragment = str(fragment if fragment is not None else getattr(table, "fragment", ""))
    fvals = np.array([_get(table.values, d.name) for d in fragment_descriptors()], dtype=float)
    pv = np.asarray(table.patch_values, dtype=float)
    names = [str(n) for n in getattr(table, "patch_names", [d.name for d in patch_descriptors()])]
    col = {n: i for i, n in enumerate(names)}
    kinds = np.asarray(getattr(table, "patch_kind", np.full(len(pv), kind))).astype(str)
    cov = getattr(table, "patch_coverage", None)
    cov = np.ones(len(pv)) if cov is None else np.asarray(cov, float)
    # a patch mostly off the fragment has no values of its own (the extractor leaves them NaN):
    # pairing it would only add imputed noise, so it is not a patch the matcher uses
    sel = np.flatnonzero((kinds == kind) & (cov >= min_coverage))
    patches = np.full((len(sel), len(patch_descriptors())), np.nan)
    for k, d in enumerate(patch_descriptors()):
        if d.name in col:
            patches[:, k] = pv[sel, col[d.name]]
    contour = np.asarray(table.contour_mm, dtype=float)
    arc = np.asarray(table.patch_arc_mm, dtype=float)[sel]
    pts, nrm, strips = _contour_geometry(contour, arc, np.asarray(getattr(table, "contour_normals", None)
                                                                 if getattr(table, "contour_normals", None) is not None else np.zeros((0, 2))))
    return FragmentCues(fragment, fvals, patches, arc, pts, nrm, strips, sel)


def _get(values, name):
    try:
        v = values[name]
    except (KeyError, IndexError, TypeError):
        return np.nan
    return np.nan if v is None else float(v)


def _contour_geometry(contour, arc, contour_normals):
    """Contour points, outward normals and centred strips at arc positions of a closed contour."""
    closed = np.vstack([contour, contour[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    length = s[-1]

    def at(q):
        q = np.mod(q, length)
        return np.stack([np.interp(q, s, closed[:, 0]), np.interp(q, s, closed[:, 1])], axis=-1)

    pts = at(arc)
    # direction that makes the signed area positive, so neighbours' shared breaks run opposite
    sign = 1.0 if signed_area_mm2(contour) >= 0 else -1.0
    if len(contour_normals) == len(contour):
        cn = np.vstack([contour_normals, contour_normals[:1]])
        nrm = np.stack([np.interp(np.mod(arc, length), s, cn[:, 0]), np.interp(np.mod(arc, length), s, cn[:, 1])], -1)
    else:
        tangent = at(arc + 0.5 * sign) - at(arc - 0.5 * sign)
        # positive area in the (x right, y down) frame: the outside lies to the left of travel
        nrm = np.stack([tangent[:, 1], -tangent[:, 0]], -1)
    nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=-1, keepdims=True), 1e-12)
    strips = []
    for half, n in _STRIPS:
        offs = np.linspace(-half, half, n) * sign
        w = at(arc[:, None] + offs[None, :])
        strips.append(w - w.mean(axis=1, keepdims=True))
    return pts, nrm, strips


def strip_gap(strips_a: np.ndarray, strips_b: np.ndarray) -> np.ndarray:
    """RMS residual (mm) of the best rigid fit of each B strip, reversed, onto the A strip.

    ``strips_a``, ``strips_b``: (K, W, 2) centred strips of paired patches (row k with row k).
    Closed-form 2-D Procrustes (see :func:`common.matching.alignment.procrustes_all_pairs`).
    """
    b = strips_b[:, ::-1, :]
    c = np.einsum("kwi,kwi->k", strips_a, b)
    s = np.einsum("kw,kw->k", strips_a[:, :, 1], b[:, :, 0]) - np.einsum("kw,kw->k", strips_a[:, :, 0], b[:, :, 1])
    na = np.einsum("kwi,kwi->k", strips_a, strips_a)
    nb = np.einsum("kwi,kwi->k", b, b)
    res = na + nb - 2.0 * np.hypot(c, s)
    return np.sqrt(np.maximum(res, 0.0) / strips_a.shape[1])


_FRAG_DESC = None
_PATCH_DESC = None


def _descs():
    global _FRAG_DESC, _PATCH_DESC
    if _FRAG_DESC is None:
        _FRAG_DESC, _PATCH_DESC = fragment_descriptors(), patch_descriptors()
    return _FRAG_DESC, _PATCH_DESC


def _rule_arrays(descs):
    rule = np.array([d.rule for d in descs])
    period = np.array([d.period if d.period > 0 else np.inf for d in descs])
    return rule == "abs_sum", rule == "angle_diff", period


_RULES_CACHE: dict = {}


def column_rules(descs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each column's correspondence rule: (is ``abs_sum``, is ``angle_diff``, angle period or inf)."""
    key = id(descs)
    if key not in _RULES_CACHE:
        _RULES_CACHE[key] = _rule_arrays(descs)
    return _RULES_CACHE[key]


def _columnwise(descs, a, b):
    """Vectorised :func:`correspondence` over columns (same rules, all columns at once)."""
    is_sum, is_angle, period = column_rules(descs)
    out = np.abs(a - b)
    if is_sum.any():
        out[..., is_sum] = np.abs(a + b)[..., is_sum]
    if is_angle.any():
        d = np.mod(out[..., is_angle], period[is_angle])
        out[..., is_angle] = np.minimum(d, period[is_angle] - d)
    return out


def pair_rows(a: FragmentCues, b: FragmentCues, ia: np.ndarray | None = None, ib: np.ndarray | None = None) -> np.ndarray:
    """Correspondence rows of patch pairs ``(a[ia[k]], b[ib[k]])`` (all pairs when omitted).

    Returns
    -------
    (K, D) float array in :func:`correspondence_columns` order; NaN where a cue is missing.

    References
    ----------
    Thesis §5.2.2 (correspondence of two feature values).
    """
    fd, pd = _descs()
    if ia is None or ib is None:
        ia, ib = np.meshgrid(np.arange(len(a)), np.arange(len(b)), indexing="ij")
        ia, ib = ia.ravel(), ib.ravel()
    ia = np.asarray(ia, int)
    ib = np.asarray(ib, int)
    k = len(ia)
    out = np.empty((k, len(fd) + len(pd) + len(MATCH_COLUMNS)))
    out[:, :len(fd)] = _columnwise(fd, a.values, b.values)[None, :]
    out[:, len(fd):len(fd) + len(pd)] = _columnwise(pd, a.patches[ia], b.patches[ib])
    for m, (sa, sb) in enumerate(zip(a.strips, b.strips)):
        out[:, len(fd) + len(pd) + m] = strip_gap(sa[ia], sb[ib])
    return out


def check_correspondence_rules() -> None:
    """Raise if the vectorised rules disagree with the registry's :func:`correspondence` (self-test)."""
    fd, pd = _descs()
    rng = np.random.default_rng(0)
    for descs in (fd, pd):
        a, b = rng.uniform(-200, 200, (2, len(descs)))
        ref = np.array([correspondence(d, x, y) for d, x, y in zip(descs, a, b)])
        if not np.allclose(_columnwise(descs, a, b), ref):
            raise AssertionError("vectorised correspondence differs from the registry")


# -- ground truth ------------------------------------------------------------------------------

def _to_wall(points, pose):
    ang, tx, ty = pose
    c, s = np.cos(np.radians(ang)), np.sin(np.radians(ang))
    r = np.array([[c, -s], [s, c]])
    return points @ r.T + np.array([tx, ty]), r


def true_patch_pairs(a: FragmentCues, pose_a, b: FragmentCues, pose_b, *, max_dist_mm: float = 2.5,
                     min_opposition: float = 0.5) -> np.ndarray:
    """Matching patch pairs of two true neighbours, from their wall poses.

    Parameters
    ----------
    a, b : FragmentCues
    pose_a, pose_b : (angle_deg, tx_mm, ty_mm)
        Fragment frame → wall: ``wall = R(angle) @ p + t``.
    max_dist_mm : float
        Largest wall distance between the two patches' contour points (half the patch spacing
        plus erosion of the break).
    min_opposition : float
        The outward normals must satisfy ``n_a · n_b ≤ −min_opposition`` (facing each other).

    Returns
    -------
    (K, 2) int array of (patch of A, patch of B) index pairs.
    """
    pa, ra = _to_wall(a.points_mm, pose_a)
    pb, rb = _to_wall(b.points_mm, pose_b)
    na, nb = a.normals @ ra.T, b.normals @ rb.T
    d = np.linalg.norm(pa[:, None, :] - pb[None, :, :], axis=-1)
    facing = (na @ nb.T) <= -min_opposition
    ok = (d <= max_dist_mm) & facing
    valid_a = np.isfinite(a.patches).any(axis=1)
    valid_b = np.isfinite(b.patches).any(axis=1)
    ok &= valid_a[:, None] & valid_b[None, :]
    return np.argwhere(ok)


def pair_group(a: str, b: str) -> int:
    """Stable integer id of an unordered fragment pair (the cross-validation group)."""
    x, y = sorted((str(a), str(b)))
    return zlib.crc32(f"{x}\0{y}".encode()) & 0x7FFFFFFF


@dataclass
class TrainingSet:
    """Labelled patch-pair correspondence rows.

    Attributes
    ----------
    x : (K, D) rows, ``columns`` names; y : (K,) 1 = matching patch pair
    groups : (K,) fragment-pair id (:func:`pair_group`): cross-validation never splits a pair
    fragments : (K, 2) str fragment ids; patches : (K, 2) int patch indices in the FragmentCues
    negatives_per_positive : float  sampling ratio of non-matches to matches
    """

    x: np.ndarray
    y: np.ndarray
    groups: np.ndarray
    fragments: np.ndarray
    patches: np.ndarray
    columns: list
    negatives_per_positive: float

    def __len__(self) -> int:
        return len(self.y)

    def concat(self, other: "TrainingSet") -> "TrainingSet":
        if other.columns != self.columns:
            raise ValueError("training sets have different columns")
        return TrainingSet(np.vstack([self.x, other.x]), np.concatenate([self.y, other.y]),
                           np.concatenate([self.groups, other.groups]), np.vstack([self.fragments, other.fragments]),
                           np.vstack([self.patches, other.patches]), self.columns, self.negatives_per_positive)


def training_set(cues: dict, poses: dict, adjacency, *, negatives_per_positive: float = 10.0,
                 max_dist_mm: float = 2.5, seed: int = 0) -> TrainingSet:
    """Training rows from ground truth: all matching patch pairs of true neighbours plus sampled
    non-matches from fragment pairs that are not neighbours.

    Parameters
    ----------
    cues : dict fragment id → FragmentCues
    poses : dict fragment id → (angle_deg, tx_mm, ty_mm), fragment frame → wall
    adjacency : iterable of (id_a, id_b, shared_length_mm)
        True neighbours (``Wall.adjacency``); pairs with an id missing from ``cues`` are skipped.
    negatives_per_positive : float
        Non-matching rows drawn per matching row. The imbalance is kept on purpose (it is the
        real one, much reduced) and handled by class weights in the classifiers.
    max_dist_mm : float
        See :func:`true_patch_pairs`.
    seed : int

    Returns
    -------
    TrainingSet
    """
    if not negatives_per_positive > 0:
        raise ValueError(f"negatives_per_positive must be positive, got {negatives_per_positive}")
    rng = np.random.default_rng(seed)
    ids = sorted(cues)
    neigh = {tuple(sorted((str(a), str(b)))) for a, b, *_ in adjacency}
    xs, frs, pts, grs = [], [], [], []
    n_pos = 0
    for a, b in sorted(neigh):
        if a not in cues or b not in cues or a not in poses or b not in poses:
            continue
        pairs = true_patch_pairs(cues[a], poses[a], cues[b], poses[b], max_dist_mm=max_dist_mm)
        if len(pairs) == 0:
            continue
        xs.append(pair_rows(cues[a], cues[b], pairs[:, 0], pairs[:, 1]))
        frs += [(a, b)] * len(pairs)
        pts.append(pairs)
        grs += [pair_group(a, b)] * len(pairs)
        n_pos += len(pairs)
    if n_pos == 0:
        raise ValueError("no matching patch pairs: check the poses, adjacency and patch tables")
    n_neg = int(round(n_pos * negatives_per_positive))
    # draw fragment pairs uniformly among non-neighbours, then a patch of each
    neg_x, neg_f, neg_p, neg_g = [], [], [], []
    drawn = 0
    while drawn < n_neg:
        i, j = rng.choice(len(ids), 2, replace=False)
        a, b = sorted((ids[i], ids[j]))
        if (a, b) in neigh or len(cues[a]) == 0 or len(cues[b]) == 0:
            continue
        m = min(8, n_neg - drawn)
        ia = rng.integers(0, len(cues[a]), m)
        ib = rng.integers(0, len(cues[b]), m)
        neg_x.append(pair_rows(cues[a], cues[b], ia, ib))
        neg_f += [(a, b)] * m
        neg_p.append(np.column_stack([ia, ib]))
        neg_g += [pair_group(a, b)] * m
        drawn += m
    x = np.vstack(xs + neg_x)
    y = np.concatenate([np.ones(n_pos, int), np.zeros(drawn, int)])
    return TrainingSet(x, y, np.array(grs + neg_g), np.array(frs + neg_f, dtype=object).astype(str),
                       np.vstack(pts + neg_p), correspondence_columns(), drawn / n_pos)
