"""The colour ribbon: do two fragments' boundary strips carry the same painting and plaster? (§5.2.1)

The thesis' ribbon matcher slides two fragments' boundary strips along each other and scores how
well they fit. On a fresco the strongest evidence across a crack is the paint: bands, lines and
colour fields continue from one fragment onto its neighbour, and so does the plaster thickness.
Each fragment's *boundary profile* (:func:`common.features.boundary.boundary_profile`: colour and
thickness sampled every ~1 mm along the contour, just inside it) is compared here with every
relative placement of the other fragment's profile, run backwards (two neighbours traverse their
shared crack in opposite directions):

1. ``D[i, j]`` — distance between sample ``i`` of A and sample ``j`` of B reversed:
   ``min(√(|√a_A − √a_B|² + w_t Δt²), √(|ã_A − ã_B|² + w_t Δt²))`` with √albedo ``√a``, the
   per-fragment standardised albedo ``ã`` (immune to fading and tints of one fragment) and the
   thickness difference ``Δt`` (mm, weight ``w_t``; skipped when a fragment has no height map).
2. *Tolerance*: ``D`` is replaced by its minimum over ±``tolerance_mm`` along either profile: the
   paint boundaries cross a crack obliquely and erosion eats the rims unevenly, so the samples of
   a true pair face each other only to within a few mm.
3. The score is minus the mean of the tolerant ``D`` over the best run of ``window_mm`` of
   consecutive facing samples (a diagonal of ``D``, wrapping around both closed contours).

A true pair's score is high; so is the score of two plain fragments of one colour, which is why
this ranks only the candidates the learned patch classifier put first (:mod:`common.matching.index`).
On the synthetic test wall the ribbon alone ranks 45–47 % of true neighbours in a fragment's top
5, against 24 % for the patch classifier (docs/matching.md).

The score becomes a join probability through a one-dimensional logistic calibration fitted on a
training wall's fragment pairs (:func:`fit_ribbon_calibration`), stored with the match model.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import minimum_filter1d

#: length of the compared run of facing samples, mm
RIBBON_WINDOW_MM = 20.0
#: positional tolerance along either profile, mm
RIBBON_TOLERANCE_MM = 3.0
#: weight of the squared thickness difference (mm²) against the squared colour distance
RIBBON_THICKNESS_WEIGHT = 0.01


def _groups(names) -> dict:
    names = list(names)
    cols = {g: [i for i, n in enumerate(names) if n.startswith(g)] for g in ("sqrt_", "std_", "thickness@")}
    if not cols["sqrt_"] or len(cols["sqrt_"]) != len(cols["std_"]):
        raise ValueError(f"boundary profile columns must include sqrt_* and std_* colour channels, got {names}")
    return cols


def _prepare(profile: np.ndarray, cols: dict):
    """(√albedo, standardised albedo, thickness or None) of one profile; NaN thickness samples take
    the profile's median thickness (no evidence either way)."""
    p = np.asarray(profile, dtype=np.float32)
    th = p[:, cols["thickness@"]] if cols["thickness@"] else np.zeros((len(p), 0), np.float32)
    good = np.isfinite(th)
    if th.size and good.any():
        med = np.array([np.median(th[good[:, c], c]) if good[:, c].any() else 0.0 for c in range(th.shape[1])],
                       np.float32)
        th = np.where(good, th, med)
    else:
        th = None
    return np.nan_to_num(p[:, cols["sqrt_"]]), np.nan_to_num(p[:, cols["std_"]]), th


def _sqdist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.maximum((a ** 2).sum(1)[:, None] + (b ** 2).sum(1)[None, :] - 2.0 * a @ b.T, 0.0)


def ribbon_scores(profile_a: np.ndarray, profiles_b: list, names, *, step_mm: float = 1.0,
                  window_mm: float = RIBBON_WINDOW_MM, tolerance_mm: float = RIBBON_TOLERANCE_MM,
                  thickness_weight: float = RIBBON_THICKNESS_WEIGHT):
    """Ribbon score of fragment A against each of several fragments B (module docstring).

    Parameters
    ----------
    profile_a : (Ka, C) array
        A's boundary profile, columns ``names``.
    profiles_b : list of (Kb, C) arrays
        The other fragments' profiles (same columns).
    names : list of str
        Column names (:func:`common.features.boundary.boundary_channel_names`).
    step_mm : float
        Arc-length step of the profiles (about 1 mm), to turn the window and tolerance into samples.
    window_mm, tolerance_mm, thickness_weight : float
        See the module docstring.

    Returns
    -------
    score : (K,) float
        Minus the mean tolerant distance over the best window (higher = better fit); NaN for an
        empty profile.
    start_a : (K,) int
        First sample of A's best window (A runs forwards from there).
    start_b : (K,) int
        First sample of B's best window (B runs backwards from there).
    """
    if not step_mm > 0:
        raise ValueError(f"step_mm must be positive, got {step_mm}")
    if not (window_mm > 0 and tolerance_mm >= 0 and thickness_weight >= 0):
        raise ValueError("window_mm must be positive, tolerance_mm and thickness_weight non-negative")
    cols = _groups(names)
    a = np.asarray(profile_a, dtype=np.float32)
    if a.ndim != 2 or a.shape[1] != len(list(names)):
        raise ValueError(f"profile_a must be (K, {len(list(names))}), got {a.shape}")
    k = len(profiles_b)
    score, start_a, start_b = np.full(k, np.nan), np.zeros(k, int), np.zeros(k, int)
    lens = np.array([len(p) for p in profiles_b], int)
    ok = np.flatnonzero(lens >= 3)
    if len(a) < 3 or not len(ok):
        return score, start_a, start_b
    na = len(a)
    tol = int(round(tolerance_mm / step_mm))
    win = max(1, min(int(round(window_mm / step_mm)), na))
    sa, za, ta = _prepare(a, cols)
    # every B reversed and padded by `tol` samples of its own wrap, stacked: one matrix product
    # gives D for all of them, and the minimum filter along B never crosses into another fragment
    parts_s, parts_z, parts_t, offsets = [], [], [], [0]
    has_t = ta is not None
    for j in ok:
        sb, zb, tb = _prepare(profiles_b[j], cols)
        nb = len(sb)
        idx = (nb - 1 - np.arange(-tol, nb + tol)) % nb      # reversed, wrapped padding
        parts_s.append(sb[idx])
        parts_z.append(zb[idx])
        parts_t.append(tb[idx] if tb is not None else None)
        offsets.append(offsets[-1] + nb + 2 * tol)
    d_t = 0.0
    if has_t and all(t is not None for t in parts_t):
        d_t = thickness_weight * _sqdist(ta, np.vstack(parts_t))
    d = np.minimum(_sqdist(sa, np.vstack(parts_s)), _sqdist(za, np.vstack(parts_z))) + d_t
    d = np.sqrt(d)
    if tol:
        d = np.minimum(minimum_filter1d(d, 2 * tol + 1, axis=0, mode="wrap"),
                       minimum_filter1d(d, 2 * tol + 1, axis=1, mode="nearest"))
    # diagonals: row r of G (one per B sample j0 of each fragment) holds D[i mod na, j0 + i mod nb]
    # for i = 0 … na + win − 1, so window sums along it are every placement of the run
    cols_idx = []
    ii = np.arange(na + win)
    for t, j in enumerate(ok):
        nb, base = lens[j], offsets[t] + tol
        cols_idx.append(base + (ii[None, :] + np.arange(nb)[:, None]) % nb)
    g = d[(ii % na)[None, :], np.vstack(cols_idx)]
    c = np.concatenate([np.zeros((len(g), 1), np.float32), np.cumsum(g, axis=1)], axis=1)
    sums = c[:, win:win + na] - c[:, :na]                 # (rows, na): run starting at A sample i
    best_i = np.argmin(sums, axis=1)
    best = sums[np.arange(len(sums)), best_i]
    bounds = np.concatenate([[0], np.cumsum(lens[ok])])
    for t, j in enumerate(ok):
        r0 = bounds[t] + int(np.argmin(best[bounds[t]:bounds[t + 1]]))
        j0 = r0 - bounds[t]
        i0 = int(best_i[r0])
        score[j] = -best[r0] / win
        start_a[j] = i0
        start_b[j] = lens[j] - 1 - (i0 + j0) % lens[j]        # back to B's own (forward) indexing
    return score, start_a, start_b


def pair_ribbon_scores(profiles: dict, names, *, step_mm: float = 1.0, progress=None) -> dict:
    """Ribbon score of every unordered pair of fragments, ``{(a, b): score}`` (a before b in
    ``profiles`` order); for training the calibration and for evaluation."""
    ids = [f for f, p in profiles.items() if p is not None and len(p) >= 3]
    out = {}
    for i, a in enumerate(ids[:-1]):
        s, _, _ = ribbon_scores(profiles[a], [profiles[b] for b in ids[i + 1:]], names, step_mm=step_mm)
        out.update({(a, b): float(v) for b, v in zip(ids[i + 1:], s)})
        if progress and (i % 10 == 0 or i == len(ids) - 2):
            progress((i + 1) / max(1, len(ids) - 1), f"ribbon scores of fragment {i + 1}/{len(ids)}")
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
