"""Grouped cross-validation, confusion rates, precision-recall and top-k recall."""

import numpy as np
import pytest

from common.matching.classifiers import CLASSIFIERS, SUBSETS, column_group, make_classifier, subset_columns
from common.matching.evaluation import (confusion_rates, grouped_cross_validation, pair_precision_recall,
                                        top_k_recall)
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


def test_pair_precision_recall_is_perfect_for_a_perfect_ranking():
    scores = {("A", "B"): 0.9, ("A", "C"): 0.1, ("B", "C"): 0.8}
    res = pair_precision_recall(scores, [("A", "B"), ("B", "C")])
    assert res["ap"] == pytest.approx(1.0)
