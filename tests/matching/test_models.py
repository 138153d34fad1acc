"""Match models round-trip through a pickle-free artifact and predict like the fitted pipeline."""

import h5py
import numpy as np
import pytest

from common.matching.classifiers import make_classifier
from common.matching.models import MatchModel, load_model, model_from_pipeline, save_model
from common.store import ArtifactError, Store


def fitted(seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(400, 4))
    y = (x[:, 0] - 0.5 * x[:, 2] + 0.3 * rng.normal(size=400) > 0).astype(int)
    x[rng.random(x.shape) < 0.05] = np.nan
    return make_classifier("logistic").fit(x, y), x


def test_model_predicts_like_the_pipeline_including_missing_values():
    pipe, x = fitted()
    m = model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=1)
    assert np.allclose(m.probability(x), pipe.predict_proba(x)[:, 1], atol=1e-9)
    assert m.version.startswith("0001-")


def test_saved_model_round_trips_and_holds_no_pickle(tmp_path):
    store = Store(tmp_path)
    pipe, x = fitted()
    m = model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=3, info={"n_train": 400})
    ref = save_model(store, m)
    back = load_model(store, ref)
    assert back.version == m.version and back.info == {"n_train": 400}
    assert np.allclose(back.probability(x), m.probability(x))
    with h5py.File(store.path(ref.path)) as f:
        kinds = {f[k].dtype.kind for k in f}
    assert kinds <= {"f", "O"}  # floats and strings only


def test_tampered_model_file_is_refused(tmp_path):
    store = Store(tmp_path)
    pipe, _ = fitted()
    ref = save_model(store, model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=1))
    with open(store.path(ref.path), "r+b") as fh:
        fh.seek(ref.bytes // 2)
        fh.write(b"\xff\xfe")
    with pytest.raises(ArtifactError):
        load_model(store, ref)


def test_model_refuses_wrong_shapes():
    with pytest.raises(ValueError, match="coef"):
        MatchModel(["a", "b"], [0, 0], [0, 0], [1, 1], [1, 2, 3], 0.0)


def test_ribbon_calibration_is_stored_versioned_and_optional(tmp_path):
    store = Store(tmp_path)
    pipe, _ = fitted()
    plain = model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=2)
    cal = model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=2, ribbon=(17.5, -1.75))
    assert plain.ribbon is None and cal.version != plain.version   # the calibration is part of the model
    assert load_model(store, save_model(store, cal)).ribbon == (17.5, -1.75)
    assert load_model(store, save_model(store, plain)).ribbon is None
    with pytest.raises(ValueError, match="ribbon"):
        model_from_pipeline(pipe, ["a", "b", "c", "d"], sequence=2, ribbon=(float("nan"), 0.0))


def test_a_model_calibrated_for_another_ribbon_score_is_calibrated_again_as_a_bootstrap_would_be(small_wall):
    """A model from before the ribbon's score changed (no definition recorded, or another) gets the calibration a fresh
    bootstrap on the same wall fits, as the next version, and keeps its patch classifier and training rows; a model
    of today's score, or without a ribbon, is left as it is."""
    from common.matching.online import bootstrap_wall, ribbon_calibration, train_model, with_current_ribbon
    from common.matching.pairs import training_set
    from common.matching.ribbon import RIBBON_DEFINITION

    wall, tables, cues, poses = small_wall
    old, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1), sequence=4, ribbon=(10.0, -3.0),
                         info={"ribbon_definition": "runs of 20 mm"})
    renewed = with_current_ribbon(old, n_fragments=12, seed=3)
    boot_wall, boot_tables, _ = bootstrap_wall(n_fragments=12, seed=3)
    assert renewed.ribbon == pytest.approx(ribbon_calibration(boot_tables, boot_wall.adjacency))
    assert renewed.ribbon != pytest.approx((10.0, -3.0))
    assert renewed.sequence == 5 and renewed.version != old.version
    assert renewed.info["ribbon_definition"] == RIBBON_DEFINITION and renewed.info["previous"] == old.version
    np.testing.assert_array_equal(renewed.coef, old.coef)
    assert renewed.training is old.training
    assert with_current_ribbon(renewed, n_fragments=12, seed=3) is renewed
    no_ribbon, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1))
    assert with_current_ribbon(no_ribbon) is no_ribbon
    fresh, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1), ribbon=(10.0, -3.0))
    assert fresh.info["ribbon_definition"] == RIBBON_DEFINITION            # recorded when trained
    assert with_current_ribbon(fresh) is fresh
