"""Mutual proximity (Schnitzer et al. 2012): a pair's standing in both fragments' rankings."""

import numpy as np
import pytest

from common.matching.mutual import mutual_pair_scores, mutual_proximity


def test_it_is_uniform_over_random_pairs():
    # the null it is built on: independent, uniform ranks give a uniform MP (its definition as a
    # probability), so a threshold of MP keeps the stated share of random pairs
    rng = np.random.default_rng(0)
    n = 200
    r_a, r_b = rng.integers(1, n + 1, 100_000), rng.integers(1, n + 1, 100_000)
    mp = mutual_proximity(r_a, n, r_b, n)
    assert np.all((mp >= 0) & (mp < 1))
    for q in (0.1, 0.5, 0.9):
        assert np.mean(mp <= q) == pytest.approx(q, abs=0.01)


def test_closed_form_and_edges():
    # rank 5 of 20 and 2 of 10: x = 0.25 * 0.2 = 0.05, MP = 1 - x (1 - ln x)
    assert mutual_proximity(5, 20, 2, 10) == pytest.approx(1 - 0.05 * (1 - np.log(0.05)))
    assert mutual_proximity(20, 20, 10, 10) == 0.0          # last in both lists
    assert mutual_proximity(1, 1000, 1, 1000) > 0.9999      # first in both
    # a side that did not rank the pair counts it as its last
    assert mutual_proximity(3, 10, None, 7) == mutual_proximity(3, 10, 7, 7)
    assert mutual_proximity(3, 10, np.nan, 7) == mutual_proximity(3, 10, 7, 7)


def test_symmetric_and_monotone():
    assert mutual_proximity(3, 10, 8, 40) == mutual_proximity(8, 40, 3, 10)
    # better on either side is never worse
    assert mutual_proximity(2, 10, 8, 40) > mutual_proximity(3, 10, 8, 40)
    assert mutual_proximity(3, 10, 7, 40) > mutual_proximity(3, 10, 8, 40)


def test_a_hub_loses_to_a_mutual_pair():
    # "h" is everyone's first candidate, but ranks them all low in its own list; "a" and "b" rank
    # each other second. By the larger of the two sides' standing the hub would be everyone's first;
    # mutual proximity puts a's true partner first.
    filler = [f"f{i}" for i in range(8)]
    rankings = {
        "a": ["h", "b", *filler],
        "b": ["h", "a", *filler],
        "h": [*filler, "b", "a"],
    }
    s = mutual_pair_scores(rankings)
    assert ("a", "b") in s and ("a", "h") in s and ("f0", "h") in s
    assert s[("a", "b")] > s[("a", "h")] and s[("a", "b")] > s[("b", "h")]
    # a pair only one side ranked: the other side counts it last
    assert s[("f0", "h")] == pytest.approx(mutual_proximity(1, 10, None, 1))


def test_bad_ranks_are_refused():
    with pytest.raises(ValueError, match="beyond its list"):
        mutual_proximity(11, 10, 1, 10)
    with pytest.raises(ValueError, match="at least one candidate"):
        mutual_proximity(1, 0, 1, 10)
