"""Grouped cross-validation, confusion rates, precision-recall and top-k recall."""

import numpy as np
import pytest

from common.matching.classifiers import CLASSIFIERS, SUBSETS, column_group, make_classifier, subset_columns
from common.matching.evaluation import (bootstrap_interval, confusion_rates, grouped_cross_validation,
                                        pair_precision_recall, top_k_counts, top_k_recall)
from common.matching.pairs import correspondence_columns


def synthetic_rows(n_groups=60, per_group=20, seed=0):
    """Rows whose first 'colour' column separates the classes and whose others are noise."""
    rng = np.random.default_rng(seed)
    cols = correspondence_columns()
    groups = np.repeat(np.arange(n_groups), per_group)
    y = (groups % 4 == 0).astype(int)   # a whole fragment pair is a match or not
    x = np.abs(rng.normal(size=(len(y), len(cols))))
    c = cols.index("patch.colour_mean_r")
    x[:, c] = np.where(y == 1, 0.1, 1.0) + 0.2 * np.abs(rng.normal(size=len(y)))
    return x, y, groups, cols


def test_confusion_rates_on_a_known_table():
    r = confusion_rates([1, 1, 1, 1, 0, 0, 0, 0, 0, 0], [1, 1, 1, 0, 0, 0, 0, 0, 1, 1])
    assert r["tpr"] == pytest.approx(0.75) and r["tnr"] == pytest.approx(4 / 6)
    assert r["fnr"] == pytest.approx(0.25) and r["fpr"] == pytest.approx(2 / 6)


@pytest.mark.parametrize("kind", CLASSIFIERS)
def test_every_classifier_learns_a_separable_cue(kind):
    x, y, groups, cols = synthetic_rows()
    res = grouped_cross_validation(x, y, groups, cols, kind=kind, subset="colour")
    assert res.rates["tpr"] > 0.9 and res.rates["tnr"] > 0.9 and res.ap > 0.9


def test_a_subset_without_the_cue_is_at_chance():
    x, y, groups, cols = synthetic_rows()
    res = grouped_cross_validation(x, y, groups, cols, subset="normal")
    assert res.ap < 0.5


def test_folds_never_split_a_fragment_pair():
    from sklearn.model_selection import GroupKFold
    x, y, groups, _ = synthetic_rows()
    for tr, te in GroupKFold(n_splits=10).split(x, y, groups):
        assert not set(groups[tr]) & set(groups[te])


def test_subsets_select_columns_by_descriptor_group():
    cols = correspondence_columns()
    for name, groups in SUBSETS.items():
        idx = subset_columns(cols, name)
        assert {column_group(cols[i]) for i in idx} <= set(groups)
    assert len(subset_columns(cols, "all")) == len(cols)
    with pytest.raises(ValueError, match="subset"):
        subset_columns(cols, "texture")
    with pytest.raises(ValueError, match="kind"):
        make_classifier("knn")


def test_top_k_recall_counts_true_neighbours_in_each_fragments_top_k():
    scores = {("A", "B"): 0.9, ("A", "C"): 0.8, ("A", "D"): 0.1, ("B", "C"): 0.5, ("C", "D"): 0.7}
    truth = [("A", "D"), ("C", "D")]
    r = top_k_recall(scores, truth, ks=(1, 2, 3))
    # A: D ranks 3rd; D: C 1st, A 2nd; C: D 2nd (after A)
    assert r[1] == pytest.approx(1 / 4)
    assert r[2] == pytest.approx(3 / 4)
    assert r[3] == pytest.approx(1.0)


def test_top_k_counts_are_the_per_fragment_terms_of_top_k_recall():
    scores = {("A", "B"): 0.9, ("A", "C"): 0.8, ("A", "D"): 0.1, ("B", "C"): 0.5, ("C", "D"): 0.7}
    truth = [("A", "D"), ("C", "D")]
    counts = top_k_counts(scores, truth, ks=(1, 2))
    # fragments in the order of the neighbour list: A, D, C
    assert counts[1][0].tolist() == [0, 1, 0] and counts[1][1].tolist() == [1, 2, 1]
    assert counts[2][0].tolist() == [0, 2, 1]


def test_bootstrap_interval_of_a_hit_rate_matches_the_normal_approximation():
    """400 fragments, half of them hits: the 90 % interval is p ± 1.645 sqrt(p (1 − p) / n) = 0.5 ± 0.041."""
    hits = np.r_[np.ones(200), np.zeros(200)]
    low, high = bootstrap_interval(hits, level=0.9, draws=8000)
    half = 1.645 * np.sqrt(0.25 / 400)
    assert low == pytest.approx(0.5 - half, abs=0.006) and high == pytest.approx(0.5 + half, abs=0.006)
    # a wider level gives a wider interval; a figure counted on fewer fragments moves more
    low95, high95 = bootstrap_interval(hits, level=0.95, draws=8000)
    assert low95 < low and high95 > high
    low_few, high_few = bootstrap_interval(hits[::10], level=0.9, draws=8000)
    assert high_few - low_few > 2.5 * (high - low)


def test_bootstrap_interval_of_a_share_of_links_resamples_whole_fragments():
    """Links counted per fragment; a fragment with many links weighs by them."""
    low, high = bootstrap_interval([0, 9], [1, 9], draws=4000)
    # a resample holds the first fragment k of 2 times: share 9·(2−k)/(9·(2−k) + k) ∈ {1, 0.9, 0}
    assert low == 0.0 and high == 1.0
    assert np.isnan(bootstrap_interval([], [])).all()   # nothing counted: no interval


def test_a_share_of_one_or_zero_gets_the_exact_binomial_bound():
    """Nothing to resample when every unit is a hit: the Clopper–Pearson bound, 0.05 ** (1 / n) at 90 %
    (n = 24: 0.883; the 'rule of three' 1 − 3/n is its 95 % one-sided approximation for large n)."""
    low, high = bootstrap_interval(np.ones(24), level=0.9)
    assert high == 1.0 and low == pytest.approx(0.05 ** (1 / 24)) and low == pytest.approx(0.883, abs=1e-3)
    assert bootstrap_interval([2, 3, 1], [2, 3, 1], level=0.9) == pytest.approx((0.05 ** (1 / 3), 1.0))
    low, high = bootstrap_interval(np.zeros(300), level=0.9)   # 5 % in each tail
    assert low == 0.0 and high == pytest.approx(3 / 300, rel=0.02)   # the rule of three


def test_bootstrap_interval_refuses_mismatched_units_and_levels():
    with pytest.raises(ValueError, match="one value per unit"):
        bootstrap_interval([1, 0], [1])
    with pytest.raises(ValueError, match="level"):
        bootstrap_interval([1, 0], level=1.5)


def test_pair_precision_recall_is_perfect_for_a_perfect_ranking():
    scores = {("A", "B"): 0.9, ("A", "C"): 0.1, ("B", "C"): 0.8}
    res = pair_precision_recall(scores, [("A", "B"), ("B", "C")])
    assert res["ap"] == pytest.approx(1.0)
