"""Mutual proximity: a pair's standing in both fragments' rankings, one symmetric score.

Each fragment's ranking is made from its own point of view: stage 2 and the docking subtract
hubness, the ribbon weighs colours by their rarity, stage 3 sets its level relative to the query's
docked candidates. A probability from one query is therefore calibrated against that query's other
candidates, not against another query's, and a pooled list that takes for each pair the larger of
the two sides' probabilities lets whichever fragments score high everywhere (big painted pieces,
the hubs) crowd every list (docs/matching.md, "Mutual proximity").

Mutual proximity (Schnitzer, Flexer, Schedl & Widmer, *Local and global scaling reduce hubs in
space*, JMLR 13 (2012) 2871–2902, eq. 7, empirical form) rescales a similarity by both objects'
own distributions of similarities: the probability that a random pair is less mutually near than
``(a, b)``, ``MP(a, b) = P(S_a < s_ab ∩ S_b < s_ba)``. Under the null of independent, uniformly
drawn ranks with ``t_a = rank of b in a's list / n_a`` and ``t_b`` alike, ``T_a T_b`` has the
distribution function ``x (1 − ln x)`` on (0, 1], so

    MP = 1 − x (1 − ln x),   x = t_a t_b

— a number in [0, 1) that orders pairs as the product of the two relative ranks, is symmetric in
the two fragments and uniform over random pairs. A pair that one side did not rank (it fell out of
that fragment's candidates) counts there as last (``t = 1``).
"""

from __future__ import annotations

import numpy as np


def mutual_proximity(rank_ab, n_a, rank_ba, n_b):
    """Mutual proximity of pairs from their 1-based ranks in both fragments' lists.

    Parameters
    ----------
    rank_ab : int or array
        Rank of b in a's list (1 = a's best candidate); ``None``/NaN/0 when a did not rank b.
    n_a : int or array
        Length of a's list (how many candidates a ranked).
    rank_ba, n_b : the same from b's side.

    Returns
    -------
    float or ndarray in [0, 1): ``1 − x (1 − ln x)`` with ``x`` the product of the relative ranks
    (module docstring); 0 for a pair last in both lists.
    """
    t = _relative_rank(rank_ab, n_a) * _relative_rank(rank_ba, n_b)
    mp = 1.0 - t * (1.0 - np.log(t))
    return float(mp) if np.ndim(mp) == 0 else mp


def _relative_rank(rank, n) -> np.ndarray:
    r = np.asarray(np.nan if rank is None else rank, float)
    n = np.asarray(n, float)
    if np.any(n < 1):
        raise ValueError(f"a ranking has at least one candidate, got n = {n}")
    ok = np.isfinite(r) & (r >= 1)
    if np.any(ok & (r > n)):
        raise ValueError(f"rank {r} beyond its list of {n}")
    return np.where(ok, r, n) / n    # not ranked: last


def mutual_of(rankings: dict, fragment: str, others) -> list[float]:
    """Mutual proximity of (``fragment``, other) for each of ``others`` from kept rankings
    (``rankings``: fragment → its candidates best first); a fragment missing from the other's
    ranking, or without one, counts as its last."""
    mine = rankings.get(fragment, ())
    pos = {o: i + 1 for i, o in enumerate(mine)}
    out = []
    for o in others:
        theirs = rankings.get(o, ())
        r_ba = theirs.index(fragment) + 1 if fragment in theirs else None
        out.append(mutual_proximity(pos.get(o), max(len(mine), 1), r_ba, max(len(theirs), 1)))
    return out


def mutual_pair_scores(rankings: dict) -> dict:
    """Mutual proximity of every pair ranked by at least one of its fragments.

    ``rankings``: fragment → its candidates best first (a list of ids). Returns ``{(a, b): MP}``
    with ``a < b``.
    """
    out = {}
    for f, order in rankings.items():
        for o, m in zip(order, mutual_of(rankings, f, order)):
            out.setdefault((f, o) if f < o else (o, f), m)
    return out
