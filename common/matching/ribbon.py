"""The colour ribbon: do two fragments' boundary strips carry the same painting and plaster? (§5.2.1)

The thesis' ribbon matcher slides two fragments' boundary strips along each other and scores how
well they fit. On a fresco the strongest evidence across a crack is the paint: bands, lines and
colour fields continue from one fragment onto its neighbour, and so does the plaster thickness.
Each fragment's *boundary profile* (:func:`common.features.boundary.boundary_profile`: colour and
thickness sampled every ~1 mm along the contour, just inside it; averaged to every
``RIBBON_STEP_MM`` by :func:`prepare_ribbon`) is compared here with every relative placement of
the other fragment's profile, run backwards (two neighbours traverse their shared crack in
opposite directions):

1. ``D[i, j]`` — distance between sample ``i`` of A and sample ``j`` of B reversed:
   ``min(√(|√a_A − √a_B|² + w_t Δt²), √(|ã_A − ã_B|² + w_t Δt²))`` with √albedo ``√a``, the
   per-fragment standardised albedo ``ã`` (immune to fading and tints of one fragment) and the
   thickness difference ``Δt`` (mm, weight ``w_t``; skipped when a fragment has no height map).
1b. *Rarity*: row ``i`` of ``D`` is lowered by A's sample's rarity (:func:`sample_rarity`: its mean
   colour distance to the 10 nearest samples of other fragments in a reference population), so a
   match of an unusual colour counts for more than a match of the colour every fragment of a
   plain field shares (top-5 recall on the two synthetic walls +0.03 / +0.04).
2. *Tolerance*: ``D`` is replaced by its minimum over ±``tolerance_mm`` along either profile: the
   paint boundaries cross a crack obliquely and erosion eats the rims unevenly, so the samples of
   a true pair face each other only to within a few mm.
3. For each run length ``w`` of ``windows_mm`` (20, 40 and 80 mm; a longer one at most a third of A's
   outline), the best run of ``w`` consecutive facing samples (a diagonal of ``D``, wrapping around both
   closed contours) and the mean tolerant ``D`` over it; the score is minus the mean of those means over
   the run lengths. A short run finds a short shared crack; the long ones ask the colours to agree along
   more of it, which tells the true partner among pieces of one painting (one wall of 240 factory pieces:
   top-5 0.130 → 0.227 by the ribbon alone; docs/matching.md, "A ribbon at three lengths, and one fresco").

A true pair's score is high; so is the score of two fragments of one plain colour, which is why
this ranks only the candidates the learned patch classifier put first (:mod:`common.matching.index`).
The synthetic-wall figures are in docs/matching.md.

The score becomes a join probability through a one-dimensional logistic calibration fitted on a
training wall's fragment pairs (:func:`fit_ribbon_calibration`), stored with the match model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from common.threads import one_blas_thread

#: lengths of the compared runs of facing samples, mm (module docstring, step 3)
RIBBON_WINDOWS_MM = (20.0, 40.0, 80.0)
#: the shortest, whose best run is the place a candidate's ribbon match is reported at
RIBBON_WINDOW_MM = min(RIBBON_WINDOWS_MM)
#: positional tolerance along either profile, mm
RIBBON_TOLERANCE_MM = 3.0
#: weight of the squared thickness difference (mm²) against the squared colour distance
RIBBON_THICKNESS_WEIGHT = 0.01
#: the profiles are compared every 2 mm (neighbouring 1 mm samples averaged): the paint changes
#: on a scale of millimetres and the tolerance is 3 mm anyway, and it is 4× cheaper than 1 mm
#: (top-5 recall on the synthetic test wall 0.458 vs 0.467)
RIBBON_STEP_MM = 2.0
#: rarity correction: a sample's distance to its RIBBON_RARITY_K nearest samples of other
#: fragments, times this weight, is taken off its distances (module docstring, step 1b)
RIBBON_RARITY_WEIGHT = 1.0
RIBBON_RARITY_K = 10
#: samples kept in the rarity reference population
RIBBON_POPULATION_SAMPLES = 10000
#: what a ribbon score means. A model's ribbon calibration holds only for scores made this way, so the model records
#: it (``info["ribbon_definition"]``); a model without it, or with another, has its ribbon calibrated again
#: (:func:`common.matching.online.with_current_ribbon`; before 2026-11-29 the score was one run of 20 mm)
RIBBON_DEFINITION = (f"mean of the best runs of {'/'.join(f'{w:g}' for w in RIBBON_WINDOWS_MM)} mm (the longer ones at "
                     f"most a third of the outline), "
                     f"±{RIBBON_TOLERANCE_MM:g} mm, {RIBBON_STEP_MM:g} mm steps, rarity {RIBBON_RARITY_WEIGHT:g} × "
                     f"{RIBBON_RARITY_K}")


@dataclass
class RibbonProfile:
    """A boundary profile prepared for :func:`ribbon_scores` (made once per fragment).

    Rows are samples every ``step_mm`` of arc from the contour start. ``rows[(kind, thick)]`` is
    the pair (query-side, other-side) of row arrays for colour kind ``"sqrt"`` or ``"std"``, with
    the weighted thickness appended (``thick`` True, only when the fragment has a height map) or
    not, shaped so that one matrix product gives squared distances (:func:`_distance_rows`).
    """

    rows: dict
    step_mm: float
    has_thickness: bool
    n: int

    def __len__(self) -> int:
        return self.n


def _distance_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows whose products are squared distances: ``[a, |a|², 1] · [−2b, 1, |b|²] = |a − b|²``
    (one BLAS product instead of three broadcast temporaries)."""
    # float64: in float32 the cancellation in |a|² + |b|² − 2a·b swamps the small distances of true pairs
    x = x.astype(np.float64)
    n2, one = (x * x).sum(axis=1, keepdims=True), np.ones((len(x), 1))
    return np.hstack([x, n2, one]), np.hstack([-2.0 * x, one, n2])


def prepare_ribbon(profile: np.ndarray, names, *, step_mm: float = 1.0, ribbon_step_mm: float = RIBBON_STEP_MM,
                   thickness_weight: float = RIBBON_THICKNESS_WEIGHT) -> RibbonProfile:
    """Prepare a boundary profile for matching: resample to ``ribbon_step_mm`` (averaging), fill
    missing thickness samples with the profile's median (no evidence either way), weight it.

    Parameters
    ----------
    profile : (K, C) array
        :func:`common.features.boundary.boundary_profile` of a fragment, columns ``names``.
    names : list of str
        Its columns (:func:`common.features.boundary.boundary_channel_names`).
    step_mm : float
        Arc step of ``profile``.
    ribbon_step_mm : float
        Arc step of the comparison.
    thickness_weight : float
        Weight of the squared thickness difference.
    """
    names = list(names)
    p = np.asarray(profile, dtype=np.float32)
    if p.ndim != 2 or p.shape[1] != len(names):
        raise ValueError(f"profile must be (K, {len(names)}) for columns {names}, got {p.shape}")
    if not (step_mm > 0 and ribbon_step_mm > 0 and thickness_weight >= 0):
        raise ValueError("step_mm and ribbon_step_mm must be positive, thickness_weight non-negative")
    cols = {g: [i for i, n in enumerate(names) if n.startswith(g)] for g in ("sqrt_", "std_", "thickness@")}
    if not cols["sqrt_"] or len(cols["sqrt_"]) != len(cols["std_"]):
        raise ValueError(f"boundary profile columns must include sqrt_* and std_* colour channels, got {names}")
    k = max(1, int(round(ribbon_step_mm / step_mm)))
    if len(p) >= 3 * k and k > 1:
        blocks = p[:len(p) // k * k].reshape(-1, k, p.shape[1])
        good = np.isfinite(blocks)
        with np.errstate(invalid="ignore", divide="ignore"):   # an all-NaN block stays NaN
            p = np.where(good, blocks, 0.0).sum(axis=1) / good.sum(axis=1)
    else:
        k = 1
    th = p[:, cols["thickness@"]]
    good = np.isfinite(th)
    has_t = bool(th.size and good.any())
    if has_t:
        med = np.array([np.median(th[good[:, c], c]) if good[:, c].any() else 0.0 for c in range(th.shape[1])],
                       np.float32)
        th = np.where(good, th, med) * np.float32(np.sqrt(thickness_weight))
    else:
        th = np.zeros((len(p), 0), np.float32)
    rows = {}
    for kind in ("sqrt", "std"):
        x = np.nan_to_num(p[:, cols[kind + "_"]])
        rows[(kind, False)] = _distance_rows(x)
        if has_t:
            rows[(kind, True)] = _distance_rows(np.hstack([x, th]))
    return RibbonProfile(rows, float(step_mm * k), has_t, len(p))


@dataclass
class RibbonPopulation:
    """Boundary samples of many fragments, the reference for :func:`sample_rarity`."""

    rows: dict              # (kind, with thickness) → (N, C + 2) other-side rows
    owner: dict             # with thickness → (N,) fragment id of each of those samples
    trees: dict = field(default_factory=dict)   # (kind, with thickness) → KD-tree of the samples, made on first use

    def tree(self, kind: str, flag: bool):
        """KD-tree of the samples' values of one colour kind (:func:`sample_rarity`)."""
        if (kind, flag) not in self.trees:
            from scipy.spatial import cKDTree

            self.trees[(kind, flag)] = cKDTree(-0.5 * self.rows[(kind, flag)][:, :-2])   # other side: −2x
        return self.trees[(kind, flag)]


def ribbon_population(profiles: dict, *, max_samples: int = RIBBON_POPULATION_SAMPLES,
                      seed: int = 0) -> RibbonPopulation:
    """A random sample (at most ``max_samples``) of the boundary samples of ``{fragment: RibbonProfile}``."""
    ids = [f for f, p in profiles.items() if len(p) >= 3]
    if not ids:
        raise ValueError("a ribbon population needs at least one profile of three samples or more")
    rng = np.random.default_rng(seed)
    rows, owner = {}, {}
    # colour only (every fragment), and with thickness (the fragments that have a height map)
    for flag, members in ((False, ids), (True, [f for f in ids if profiles[f].has_thickness])):
        if not members:
            continue
        own = np.concatenate([np.full(len(profiles[f]), f, dtype=object) for f in members])
        keep = np.arange(len(own))
        if len(keep) > max_samples:
            keep = np.sort(rng.choice(len(own), max_samples, replace=False))
        owner[flag] = own[keep]
        for kind in ("sqrt", "std"):
            rows[(kind, flag)] = np.vstack([profiles[f].rows[(kind, flag)][1] for f in members])[keep]
    return RibbonPopulation(rows, owner)


def sample_rarity(a: RibbonProfile, population: RibbonPopulation, *, fragment=None,
                  k: int = RIBBON_RARITY_K) -> np.ndarray:
    """How unusual each boundary sample of A is: the mean distance (colour, and thickness when A
    has it) to its ``k`` nearest samples of *other* fragments in ``population`` (samples of
    ``fragment`` excluded), (K,).

    A match of a rare colour is stronger evidence than a match of the colour of a whole field; this
    is the mean-centred similarity against hubs (CSLS, Conneau et al., ICLR 2018) at the level of
    boundary samples.
    """
    flag = bool(a.has_thickness and True in population.owner)
    own = population.owner[flag] == fragment       # A's own samples are not its neighbours
    n_own = int(own.sum())
    k = max(1, min(k, len(own) - n_own))
    if not len(a):
        return np.zeros(0)
    # The k nearest under the smaller of the two kinds' distances are among each kind's k nearest
    # (a sample nearest by its smaller distance has k others nearer in that kind otherwise), so two
    # KD-tree queries of k + (A's own samples) neighbours each hold them: exact, without the
    # K × population distance matrices.
    m = min(len(own), k + n_own)
    xs = {kind: a.rows[(kind, flag)][0][:, :-2] for kind in ("sqrt", "std")}
    idx = np.hstack([population.tree(kind, flag).query(xs[kind], k=m)[1].reshape(len(a), m)
                     for kind in ("sqrt", "std")])
    idx.sort(axis=1)
    d2 = None
    for kind in ("sqrt", "std"):
        diff = xs[kind][:, None, :] + 0.5 * population.rows[(kind, flag)][idx, :-2]   # x_A − x_pop
        dk = np.einsum("ijk,ijk->ij", diff, diff)
        d2 = dk if d2 is None else np.minimum(d2, dk)
    d2[own[idx]] = np.inf
    d2[:, 1:][idx[:, 1:] == idx[:, :-1]] = np.inf     # a sample both queries found counts once
    part = np.partition(d2, k - 1, axis=1)[:, :k]
    return np.sqrt(np.where(np.isfinite(part), part, 0.0)).mean(axis=1)


def _shifted_min(d: np.ndarray, tol: int, axis: int) -> np.ndarray:
    """Minimum over ±tol samples along ``axis``: wrapped around a closed profile (axis 0), or
    inside padded segments (axis 1, where the padding supplies the wrap; at the array's ends the
    window is cut short)."""
    if axis == 0:   # wrap: the last rows before the first, the first after the last
        d = d[np.arange(-tol, len(d) + tol) % len(d)]
        kernel = np.ones((2 * tol + 1, 1), np.uint8)
        return cv2.erode(d, kernel, borderType=cv2.BORDER_REPLICATE)[tol:-tol]
    return cv2.erode(d, np.ones((1, 2 * tol + 1), np.uint8), borderType=cv2.BORDER_REPLICATE)


def ribbon_scores(a: RibbonProfile, others: list, *, rarity: np.ndarray | None = None,
                  windows_mm=RIBBON_WINDOWS_MM, tolerance_mm: float = RIBBON_TOLERANCE_MM,
                  rarity_weight: float = RIBBON_RARITY_WEIGHT):
    """Ribbon score of fragment A against each of several fragments B (module docstring).

    Parameters
    ----------
    a : RibbonProfile
        A's prepared profile (:func:`prepare_ribbon`).
    others : list of RibbonProfile
        The other fragments' prepared profiles (same columns and weights).
    rarity : (Ka,) array, optional
        :func:`sample_rarity` of A's samples; ``rarity_weight`` × it is taken off A's distances.
    windows_mm : sequence of float
        Lengths of the compared runs (the shortest at most A's perimeter, the others at most a third of it, but
        never below the shortest); the score is the mean over them.
    tolerance_mm, rarity_weight : float
        Positional tolerance, weight of the rarity (module docstring).

    Returns
    -------
    score : (K,) float
        Minus the mean, over the run lengths, of the mean tolerant distance over the best run of that
        length (higher = better fit); NaN for a profile shorter than three samples.
    arc_a_mm : (K,) float
        Arc position on A where the best run of the shortest length starts (A runs forwards from there).
    arc_b_mm : (K,) float
        Arc position on B where it starts (B runs backwards from there).
    """
    windows = np.atleast_1d(np.asarray(windows_mm, float))
    if not (len(windows) and np.all(windows > 0) and tolerance_mm >= 0):
        raise ValueError(f"windows_mm must be one or more positive lengths and tolerance_mm non-negative, "
                         f"got {windows_mm}, {tolerance_mm}")
    # small matrix products: BLAS threads only add overhead (and fight the other workers)
    with one_blas_thread():
        return _ribbon_scores(a, others, np.sort(windows), tolerance_mm,
                              None if rarity is None else rarity_weight * np.asarray(rarity, float))


#: cells of D handled at once (a group of candidates): small enough that the passes over it run in
#: the processor's cache, not in main memory (2.6× faster than all candidates at once)
RIBBON_BLOCK_CELLS = 1 << 17


def _ribbon_scores(a, others, windows_mm, tolerance_mm, offset):
    k = len(others)
    score, arc_a, arc_b = np.full(k, np.nan), np.zeros(k), np.zeros(k)
    lens = np.array([len(p) for p in others], int)
    ok = np.flatnonzero(lens >= 3)
    if len(a) < 3 or not len(ok):
        return score, arc_a, arc_b
    na = len(a)
    if offset is not None:
        if offset.shape != (na,):
            raise ValueError(f"rarity must be ({na},), one value per sample of A, got {offset.shape}")
        offset = offset.astype(np.float32)[:, None]
    tol = int(round(tolerance_mm / a.step_mm))
    steps = [max(1, min(int(round(w / a.step_mm)), na)) for w in windows_mm]   # shortest first
    # a longer run covers at most a third of A's outline (never less than the shortest): a shared crack rarely
    # runs further round a piece, and on a piece 3 cm across a run of 80 mm would be its whole outline
    wins = [steps[0]] + [min(n, max(steps[0], na // 3)) for n in steps[1:]]
    width = lens + 2 * tol + max(wins)       # columns of each B: reversed, padded with its own wrap
    budget = max(1, RIBBON_BLOCK_CELLS // na)
    # thickness counts only where both fragments have it (a colour-only scan is not a mismatch)
    thick = np.array([a.has_thickness and others[j].has_thickness for j in range(k)])
    for flag in (True, False):
        sel = ok[thick[ok] == flag]
        start = 0
        while start < len(sel):
            stop = start + max(1, int(np.searchsorted(np.cumsum(width[sel[start:]]), budget, side="right")))
            group = sel[start:stop]
            means, i0, j0 = _ribbon_group(a, [others[j] for j in group], flag, tol, wins, offset)
            score[group] = -means
            arc_a[group] = i0 * a.step_mm
            arc_b[group] = [(lens[j] - 1 - jj) * others[j].step_mm for j, jj in zip(group, j0)]   # B's own forward arc
            start = stop
    return score, arc_a, arc_b


def _ribbon_group(a, group, flag, tol, wins, offset):
    """Best runs of A against each B of ``group`` (all with thickness ``flag``) for each run length of
    ``wins`` (samples, shortest first): the mean over the lengths of the best run's mean tolerant distance,
    and A's and B's (reversed order) start samples of the shortest length's best run, each (len(group),)."""
    na, wmax = len(a), max(wins)
    lens = np.array([len(p) for p in group], int)
    # every B reversed and padded with its own wrap — `tol` samples before, `tol + wmax` after — and
    # stacked: one matrix product gives D for all of them, the tolerance along B never reaches into
    # another fragment, and a run of up to `wmax` samples from any start stays inside its fragment's block
    idx = [(n - 1 - np.arange(-tol, n + tol + wmax)) % n for n in lens]
    offsets = np.concatenate([[0], np.cumsum(lens + 2 * tol + wmax)])
    dd = None
    for kind in ("sqrt", "std"):
        o = np.vstack([p.rows[(kind, flag)][1][ix] for p, ix in zip(group, idx)])
        m = a.rows[(kind, flag)][0] @ o.T       # float64: see _distance_rows
        dd = m if dd is None else np.minimum(dd, m, out=dd)
    np.maximum(dd, 0.0, out=dd)
    d = np.sqrt(dd, out=dd).astype(np.float32)   # distances: float32 from here on
    if offset is not None:
        d -= offset
    if tol:
        d = np.minimum(_shifted_min(d, tol, 0), _shifted_min(d, tol, 1))
    # a run starting at A sample i and B sample j is the diagonal D[i + t, j + t], t < w (A wraps: its
    # first rows appended; B's padding holds its wrap). The shortest length's run sums come from `w0`
    # shifted views of D; a longer run is made of whole runs of the shortest, shifted along the
    # diagonal, and the samples left over (20, 40 and 80 mm: 10 + 1 + 3 additions, not 10 + 20 + 40)
    w0 = wins[0]
    d = np.vstack([d, d[:wmax - 1]])
    rows, cols = na + wmax - w0, offsets[-1] - w0 + 1
    base = d[:rows, :cols].copy()
    for t in range(1, w0):
        base += d[t:t + rows, t:t + cols]
    n_cols = offsets[-1] - wmax + 1
    starts = offsets[:-1] + tol                       # column starts[t] + j: runs starting at B sample j
    total = np.zeros(len(group))
    out_i, out_j = np.zeros(len(group), int), np.zeros(len(group), int)
    for w in wins:
        sums = base[:na, :n_cols].copy()
        for m in range(1, w // w0):
            sums += base[m * w0:m * w0 + na, m * w0:m * w0 + n_cols]
        for t in range(w // w0 * w0, w):
            sums += d[t:t + na, t:t + n_cols]
        best_i = np.argmin(sums, axis=0)              # the best A start for every column
        best = sums[best_i, np.arange(n_cols)]
        for t, n in enumerate(lens):
            j = int(np.argmin(best[starts[t]:starts[t] + n]))
            total[t] += best[starts[t] + j] / w
            if w == wins[0]:
                out_i[t], out_j[t] = best_i[starts[t] + j], j
    return total / len(wins), out_i, out_j


def _ribbon_scorer(profiles: dict, names, step_mm: float):
    """The fragments whose profile is long enough to score, and a function scoring one of them against others
    from its own side (its samples' rarity in the population of all of them): ``(ids, score(a, others) → (K,))``."""
    prepared = {f: prepare_ribbon(p, names, step_mm=step_mm) for f, p in profiles.items()
                if p is not None and len(p) >= 3}
    population = ribbon_population(prepared) if prepared else None

    def score(a, others):
        return ribbon_scores(prepared[a], [prepared[b] for b in others],
                             rarity=sample_rarity(prepared[a], population, fragment=a))[0]

    return list(prepared), score


def pair_ribbon_scores(profiles: dict, names, *, step_mm: float = 1.0, progress=None) -> dict:
    """Ribbon score of every unordered pair of fragments from their boundary profiles,
    ``{(a, b): score}`` (a before b in ``profiles`` order, scored from a's side); the sample a ribbon
    calibration is fitted on. To rank, use :func:`ribbon_rankings` (each fragment from its own side)."""
    ids, score = _ribbon_scorer(profiles, names, step_mm)
    out = {}
    for i, a in enumerate(ids[:-1]):
        s = score(a, ids[i + 1:])
        out.update({(a, b): float(v) for b, v in zip(ids[i + 1:], s)})
        if progress and (i % 10 == 0 or i == len(ids) - 2):
            progress((i + 1) / max(1, len(ids) - 1), f"ribbon scores of fragment {i + 1}/{len(ids)}")
    return out


def ribbon_rankings(profiles: dict, names, *, step_mm: float = 1.0) -> dict:
    """Every fragment's own ranking of all the others by the ribbon alone, ``{fragment: [others, best
    first]}``: each scored from its own side (its rarity, its run lengths), as stage 2½ ranks a query.

    The ribbon's longer runs are capped by the query's outline (:func:`ribbon_scores`), so scores from
    different sides are on different scales; pooling these lists by mutual proximity
    (:func:`~common.matching.mutual.mutual_pair_scores`) compares ranks instead, as the station does.
    Fragments whose profile is too short to score are left out; NaN scores go last."""
    ids, score = _ribbon_scorer(profiles, names, step_mm)
    out = {}
    for a in ids:
        others = [b for b in ids if b != a]
        s = score(a, others)
        out[a] = [others[i] for i in np.argsort(-np.nan_to_num(s, nan=-np.inf), kind="stable")]
    return out


def fit_ribbon_calibration(scores, joined) -> tuple[float, float]:
    """Logistic calibration ``p = σ(slope · score + intercept)`` of ribbon scores.

    Parameters
    ----------
    scores : (N,) float
        Ribbon scores of fragment pairs of a training wall.
    joined : (N,) bool
        Whether each pair shares a crack (ground truth or verdicts).

    Returns
    -------
    (slope, intercept) : the fitted coefficients; the pairs' own class balance is kept, so the
    probability is that of a join among pairs like the training ones (no class re-weighting).
    """
    from sklearn.linear_model import LogisticRegression

    s = np.asarray(scores, float).reshape(-1)
    y = np.asarray(joined, bool).reshape(-1)
    keep = np.isfinite(s)
    s, y = s[keep], y[keep]
    if len(s) != len(y) or len(np.unique(y)) < 2:
        raise ValueError("fit_ribbon_calibration needs finite scores of both joined and separate pairs")
    lr = LogisticRegression(C=1e4).fit(s[:, None], y)
    return float(lr.coef_[0, 0]), float(lr.intercept_[0])


def ribbon_probability(score, calibration: tuple[float, float]) -> np.ndarray:
    """Join probability of ribbon scores under a calibration ``(slope, intercept)``."""
    slope, intercept = calibration
    z = slope * np.asarray(score, float) + intercept
    return 1.0 / (1.0 + np.exp(-np.clip(z, -60, 60)))
