"""Versioned match models stored as plain numbers (no pickle) (thesis §5.8).

A model file is a ``tessera.matchmodel`` HDF5 artifact under ``models/matcher/<version>.h5``
holding only arrays and strings: the correspondence column names, the imputation values for
missing features, the standardisation (mean, scale), the logistic-regression coefficients and
intercept, the pair-aggregation rule and the per-fragment pruning weights, and (attributes
``ribbon_slope``, ``ribbon_intercept``, optional) the calibration of the colour-ribbon score, and
(``docking_slope``, ``docking_intercept``, optional) that of the docking contact, and (``combination``,
optional) the learned combination of the stage scores in stage 3. Loading reads those
numbers back; nothing is executed, so a model file from another lab is safe to open (unlike a
pickled scikit-learn estimator, which can run arbitrary code when loaded).
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field

import numpy as np

from common.store import ArtifactError, ArtifactRef, Store

SCHEMA = "tessera.matchmodel"
SCHEMA_VERSION = 1
MODEL_DIR = "models/matcher"
#: stage 3's learned combination (:attr:`MatchModel.combination`) weighs these stage scores, as logits
COMBINATION_TERMS = ("patch", "ribbon", "docking", "paint")


@dataclass
class MatchModel:
    """A linear (logistic) patch-pair match model: ``p = σ(w · (x̃ − μ) / s + b)``.

    Attributes
    ----------
    columns : list of str
        Correspondence columns in order (see :func:`common.matching.pairs.correspondence_columns`).
    impute : (D,) float
        Value used for a missing (NaN) correspondence: the training mean, so a missing cue
        contributes nothing to the logit.
    mean, scale : (D,) float
        Standardisation.
    coef : (D,) float
        Logistic-regression weights on the standardised columns.
    intercept : float
    version : str
        ``"<sequence>-<digest>"``, e.g. ``"0003-1a2b3c4d"``; the sequence orders versions.
    top_m : int
        A fragment pair's probability is the mean of its ``top_m`` best patch-pair probabilities.
    info : dict
        Provenance: training set, class weighting, number of verified pairs, ...
    training : (x, y, weight) or None
        The bootstrap training rows, kept so online refits start from them (stored as arrays).
    ribbon : (slope, intercept) or None
        Calibration of the colour-ribbon score into a join probability
        (:func:`common.matching.ribbon.fit_ribbon_calibration`); None: rank by the patch
        probability alone (a model trained without boundary profiles).
    docking : (slope, intercept) or None
        Calibration of the hubness-corrected docking contact (mm, :mod:`common.matching.docking`)
        into a join probability (stage 3, :meth:`common.matching.index.MatchIndex.rank`); None:
        no docking (models made before it).
    combination : 9 floats or None
        Stage 3's learned combination of the stage scores of a docked candidate
        (:meth:`combined_probability`): weights of the :data:`COMBINATION_TERMS` (4), intercept, and
        the value each term takes when missing (4). Fitted on synthetic pairs
        (:func:`common.matching.online.stage_combination`); None: stage 3 adds the earlier evidence and
        the paint to the docking's logit by fixed rules (:meth:`common.matching.index.MatchIndex.rank`).
    """

    columns: list[str]
    impute: np.ndarray
    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    intercept: float
    version: str = "0000-untrained"
    top_m: int = 3
    info: dict = field(default_factory=dict)
    training: tuple | None = field(default=None, repr=False)
    ribbon: tuple | None = None
    docking: tuple | None = None
    combination: tuple | None = None

    def __post_init__(self):
        self.columns = [str(c) for c in self.columns]
        d = len(self.columns)
        for name in ("impute", "mean", "scale", "coef"):
            arr = np.asarray(getattr(self, name), dtype=float).reshape(-1)
            if arr.shape != (d,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"model {name} must be {d} finite numbers, got shape {arr.shape}")
            setattr(self, name, arr)
        if np.any(self.scale <= 0):
            raise ValueError("model scale must be positive")
        self.intercept = float(self.intercept)
        if self.top_m < 1:
            raise ValueError(f"top_m must be ≥ 1, got {self.top_m}")
        if self.ribbon is not None:
            r = tuple(float(v) for v in self.ribbon)
            if len(r) != 2 or not all(np.isfinite(r)):
                raise ValueError(f"model ribbon calibration must be two finite numbers, got {self.ribbon}")
            self.ribbon = r
        if self.docking is not None:
            r = tuple(float(v) for v in self.docking)
            if len(r) != 2 or not all(np.isfinite(r)):
                raise ValueError(f"model docking calibration must be two finite numbers, got {self.docking}")
            self.docking = r
        if self.combination is not None:
            r = tuple(float(v) for v in self.combination)
            if len(r) != 2 * len(COMBINATION_TERMS) + 1 or not all(np.isfinite(r)):
                raise ValueError(f"model combination must be {2 * len(COMBINATION_TERMS) + 1} finite numbers, "
                                 f"got {self.combination}")
            if self.docking is None:
                raise ValueError("a model combination needs the docking calibration (its terms are in its units)")
            self.combination = r

    @property
    def sequence(self) -> int:
        return int(self.version.split("-", 1)[0])

    def decision(self, x: np.ndarray) -> np.ndarray:
        """Logit of (K, D) correspondence rows (NaN = missing cue)."""
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != len(self.columns):
            raise ValueError(f"x must be (K, {len(self.columns)}), got {x.shape}")
        w, constant = self.linear()
        x = np.where(np.isnan(x), self.impute, x)   # missing values take the imputed value
        return x @ w + constant

    def linear(self) -> tuple[np.ndarray, float]:
        """The decision function on raw correspondence rows: ``logit = x · w + constant``.

        Folded from the standardised model, ``w·(x − μ)/s + b = x·(w/s) + (b − μ·w/s)``, so a caller
        can add up one column at a time without building the rows (stage 2,
        :meth:`common.matching.index.MatchIndex.score`).
        """
        w = self.coef / self.scale
        return w, float(self.intercept - self.mean @ w)

    def probability(self, x: np.ndarray) -> np.ndarray:
        """Match probability of (K, D) correspondence rows."""
        return 1.0 / (1.0 + np.exp(-np.clip(self.decision(x), -60, 60)))

    def stage_terms(self, patch_logit, ribbon_score, contact_mm, paint_mm) -> np.ndarray:
        """The :data:`COMBINATION_TERMS` of candidates as logits, (N, 4), NaN where a stage did not score.

        ``patch``: stage 2's hubness-corrected logit; ``ribbon``: the ribbon score through the ribbon
        calibration; ``docking``: the hub-corrected docking contact (mm) through the docking
        calibration; ``paint``: the paint continuity (mm of crack) times the docking calibration's slope
        (a millimetre of continuing paint as a millimetre of contact, :func:`common.matching.paint.with_paint`).
        """
        if self.docking is None:
            raise ValueError("stage terms need the model's docking calibration")
        rs, rb = self.ribbon if self.ribbon is not None else (np.nan, np.nan)
        ds, db = self.docking
        return np.column_stack([np.asarray(patch_logit, float), rs * np.asarray(ribbon_score, float) + rb,
                                ds * np.asarray(contact_mm, float) + db, ds * np.asarray(paint_mm, float)])

    def combined_probability(self, patch_logit, ribbon_score, contact_mm, paint_mm) -> np.ndarray:
        """Join probability of docked candidates from all their stage scores (stage 3):
        ``σ(Σ_k w_k t_k + b)`` over the :meth:`stage_terms` ``t`` (a missing term takes its stored
        value), with the learned :attr:`combination`."""
        if self.combination is None:
            raise ValueError("the model has no learned stage combination")
        n = len(COMBINATION_TERMS)
        c = np.asarray(self.combination)
        t = self.stage_terms(patch_logit, ribbon_score, contact_mm, paint_mm)
        t = np.where(np.isfinite(t), t, c[n + 1:])
        return 1.0 / (1.0 + np.exp(-np.clip(t @ c[:n] + c[n], -60, 60)))

    def column_weights(self, columns: list[str]) -> np.ndarray:
        """|w| / s for ``columns`` (0 where absent): the weighted-L1 pruning metric (§5.2.1)."""
        idx = {c: i for i, c in enumerate(self.columns)}
        return np.array([abs(self.coef[idx[c]]) / self.scale[idx[c]] if c in idx else 0.0 for c in columns])

    def digest(self) -> str:
        from common.store import content_key
        return content_key(json.dumps(self.columns), self.impute.tobytes().hex(), self.mean.tobytes().hex(),
                           self.scale.tobytes().hex(), self.coef.tobytes().hex(), repr(self.intercept),
                           str(self.top_m), *([repr(self.ribbon)] if self.ribbon is not None else []),
                           *([f"docking {self.docking!r}"] if self.docking is not None else []),
                           *([f"combination {self.combination!r}"] if self.combination is not None else []), length=8)


def model_from_pipeline(pipeline, columns: list[str], *, sequence: int, top_m: int = 3, info: dict | None = None,
                        ribbon: tuple | None = None, docking: tuple | None = None,
                        combination: tuple | None = None) -> MatchModel:
    """Extract the numbers of a fitted logistic pipeline (from :func:`make_classifier`) into a model."""
    imp = pipeline.named_steps["impute"]
    sc = pipeline.named_steps["scale"]
    clf = pipeline.named_steps["clf"]
    if not hasattr(clf, "coef_"):
        raise ValueError("only a linear (logistic) classifier can be stored as a MatchModel")
    m = MatchModel(columns=list(columns), impute=imp.statistics_, mean=sc.mean_, scale=sc.scale_,
                   coef=clf.coef_.ravel(), intercept=float(clf.intercept_[0]), top_m=top_m, info=dict(info or {}),
                   ribbon=ribbon, docking=docking, combination=combination)
    m.version = f"{int(sequence):04d}-{m.digest()}"
    return m


def save_model(store: Store, model: MatchModel, *, provenance: dict | None = None) -> ArtifactRef:
    """Write a model as an immutable ``tessera.matchmodel`` artifact at ``models/matcher/<version>.h5``."""

    def fill(f):
        f.attrs["version"] = model.version
        f.attrs["top_m"] = int(model.top_m)
        f.attrs["intercept"] = float(model.intercept)
        f.attrs["info"] = json.dumps(model.info, default=str, sort_keys=True)
        f.attrs["saved"] = _dt.datetime.now(_dt.timezone.utc).isoformat()
        if model.ribbon is not None:
            f.attrs["ribbon_slope"], f.attrs["ribbon_intercept"] = model.ribbon
        if model.docking is not None:
            f.attrs["docking_slope"], f.attrs["docking_intercept"] = model.docking
        if model.combination is not None:
            f.attrs["combination"] = np.asarray(model.combination, np.float64)
        f.create_dataset("columns", data=np.array(model.columns, dtype=object), dtype=_str_dtype())
        for name in ("impute", "mean", "scale", "coef"):
            f.create_dataset(name, data=getattr(model, name).astype(np.float64))
        if model.training is not None:
            x, y, w = model.training
            g = f.create_group("training")
            g.create_dataset("x", data=np.asarray(x, np.float64), compression="gzip", shuffle=True)
            g.create_dataset("y", data=np.asarray(y, np.int8))
            g.create_dataset("weight", data=np.asarray(w, np.float64))

    return store.write(f"{MODEL_DIR}/{model.version}.h5", SCHEMA, SCHEMA_VERSION, fill,
                       provenance=provenance or {"model": model.version})


def load_model(store: Store, ref: ArtifactRef | dict | str) -> MatchModel:
    """Read a model artifact (digest-checked when given a pointer); only numbers and strings are read."""
    with store.open(ref, schema=SCHEMA, version=SCHEMA_VERSION) as f:
        try:
            cols = [c.decode() if isinstance(c, bytes) else str(c) for c in f["columns"][()]]
            training = None
            if "training" in f:
                g = f["training"]
                training = (g["x"][()].astype(float), g["y"][()].astype(int), g["weight"][()].astype(float))
            return MatchModel(columns=cols, impute=f["impute"][()], mean=f["mean"][()], scale=f["scale"][()],
                              coef=f["coef"][()], intercept=float(f.attrs["intercept"]),
                              version=str(f.attrs["version"]), top_m=int(f.attrs["top_m"]),
                              info=json.loads(f.attrs.get("info", "{}")), training=training,
                              ribbon=((float(f.attrs["ribbon_slope"]), float(f.attrs["ribbon_intercept"]))
                                      if "ribbon_slope" in f.attrs else None),
                              docking=((float(f.attrs["docking_slope"]), float(f.attrs["docking_intercept"]))
                                       if "docking_slope" in f.attrs else None),
                              combination=(tuple(float(v) for v in f.attrs["combination"])
                                           if "combination" in f.attrs else None))
        except (KeyError, ValueError) as exc:
            raise ArtifactError(f"model {getattr(ref, 'path', ref)} is malformed: {exc}") from exc


def _str_dtype():
    import h5py
    return h5py.string_dtype(encoding="utf-8")
