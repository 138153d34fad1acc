"""Classifiers and feature subsets for patch-pair matching (thesis §5.2.2, §5.8, Table 5.3).

A training row is the correspondence vector of one patch pair (see :mod:`common.matching.pairs`);
its columns are named ``"fragment.<descriptor>"``, ``"patch.<descriptor>"`` (the registry keys of
:data:`common.features.registry.DESCRIPTORS`) or ``"match.<score>"`` (the per-match strip fit).
A *subset* selects columns by the descriptor group, as in the thesis' Table 5.3.

Class imbalance: a wall has far more non-matching than matching patch pairs. Every classifier here
weights the classes inversely to their frequency (scikit-learn ``class_weight='balanced'``), so the
training set may keep its natural imbalance; the sampling ratio is reported with each result.
"""

from __future__ import annotations

import numpy as np
from sklearn.ensemble import RandomForestClassifier
from sklearn.impute import SimpleImputer
from sklearn.linear_model import LogisticRegression
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import StandardScaler
from sklearn.svm import SVC
from sklearn.tree import DecisionTreeClassifier

from common.features.registry import DESCRIPTORS

#: classifier kinds accepted by :func:`make_classifier`
CLASSIFIERS = ("logistic", "tree", "forest", "svm")

#: per-match columns (the strip fit of :func:`common.matching.pairs.strip_gap`)
MATCH_COLUMNS = ("match.gap_10mm", "match.gap_20mm")

#: subset name -> descriptor groups (``'match'`` = per-match columns)
SUBSETS: dict[str, frozenset] = {
    "colour": frozenset({"colour"}),
    "curvature": frozenset({"curvature"}),
    "normal": frozenset({"normal"}),
    "erosion": frozenset({"erosion"}),
    "thickness": frozenset({"thickness"}),
    "per-match": frozenset({"match"}),
    "all": frozenset({"colour", "curvature", "normal", "erosion", "thickness", "match"}),
}


def column_group(column: str) -> str:
    """Descriptor group of a correspondence column (``'match'`` for per-match columns)."""
    if column.startswith("match."):
        return "match"
    d = DESCRIPTORS.get(column)
    if d is None:
        raise ValueError(f"unknown correspondence column {column!r}")
    return d.group


def subset_columns(columns: list[str], subset: str | list[str]) -> np.ndarray:
    """Indices of ``columns`` in a named subset (or the union of several names).

    Parameters
    ----------
    columns : list of str
        Correspondence column names.
    subset : str or list of str
        Names from :data:`SUBSETS` (``'colour'``, ``'curvature'``, ``'normal'``, ``'erosion'``,
        ``'thickness'``, ``'per-match'``, ``'all'``), e.g. ``['normal', 'curvature']``.
    """
    names = [subset] if isinstance(subset, str) else list(subset)
    groups = set()
    for n in names:
        if n not in SUBSETS:
            raise ValueError(f"subset must be one of {sorted(SUBSETS)}, got {n!r}")
        groups |= SUBSETS[n]
    idx = np.array([i for i, c in enumerate(columns) if column_group(c) in groups], dtype=int)
    if idx.size == 0:
        raise ValueError(f"subset {subset!r} selects none of the {len(columns)} columns")
    return idx


def make_classifier(kind: str = "logistic", *, random_state: int = 0, C: float = 1.0) -> Pipeline:
    """A fresh scikit-learn pipeline: mean imputation → standardisation → classifier.

    Parameters
    ----------
    kind : {'logistic', 'tree', 'forest', 'svm'}
        Logistic regression (default; calibrated probabilities for ranking, §5.8), a decision
        tree, a random forest, or an RBF support-vector machine (ranked by its decision value).
    random_state : int
    C : float
        Inverse regularisation of the logistic regression and SVM.

    Notes
    -----
    All use ``class_weight='balanced'`` (see the module notes). Missing correspondences (NaN,
    e.g. normal cues of colour-only scans) are imputed with the training mean.
    """
    if kind == "logistic":
        clf = LogisticRegression(C=C, class_weight="balanced", max_iter=2000)
    elif kind == "tree":
        clf = DecisionTreeClassifier(max_depth=8, min_samples_leaf=5, class_weight="balanced",
                                     random_state=random_state)
    elif kind == "forest":
        clf = RandomForestClassifier(n_estimators=100, min_samples_leaf=2, class_weight="balanced",
                                     n_jobs=1, random_state=random_state)
    elif kind == "svm":
        clf = SVC(C=C, kernel="rbf", gamma="scale", class_weight="balanced")
    else:
        raise ValueError(f"kind must be one of {CLASSIFIERS}, got {kind!r}")
    # keep_empty_features: a column that is all-NaN in a colour-only training set stays (as 0)
    return Pipeline([("impute", SimpleImputer(strategy="mean", keep_empty_features=True)),
                     ("scale", StandardScaler()), ("clf", clf)])


def match_scores(pipeline: Pipeline, x: np.ndarray) -> np.ndarray:
    """Ranking score of rows: the match probability, or the SVM decision value."""
    if hasattr(pipeline, "predict_proba") and hasattr(pipeline.named_steps["clf"], "predict_proba") \
            and not isinstance(pipeline.named_steps["clf"], SVC):
        return pipeline.predict_proba(x)[:, 1]
    return pipeline.decision_function(x)
