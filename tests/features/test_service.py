"""The feature stage service (services/features.py) and the ``tessera features`` command
(services/cli/features.py)."""

import json
import logging

import numpy as np
import pytest

import services.features as stage
from common.features import load_features
from common.messages import MessageError, new_message, validate
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import ArtifactError, Store
from services.cli import main as tessera


class _Ctx:
    def __init__(self, store):
        self.store, self.config, self.log = store, {}, logging.getLogger("test.features")
        self.calls = []
        self.progress = lambda f, t: self.calls.append(f)


def _rgbn(normals=True):
    yy, xx = np.mgrid[:200, :200]
    mask = (yy - 100) ** 2 + ((xx - 100) * 1.2) ** 2 < 80 ** 2
    n = np.zeros((200, 200, 3), np.float32)
    n[..., 0] = 0.1 * np.sin(2 * np.pi * xx / 12)
    n[..., 2] = 1
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return RGBNImage(np.full((200, 200, 3), 0.4), mask, 150.0, normals=n if normals else None)


@pytest.fixture
def store_with_rgbn(tmp_path):
    store = Store(tmp_path)
    ref = save_rgbn(store, "fragments/F7/rgbn/front-abc.h5", _rgbn())
    return store, ref


def test_rgbn_ready_gives_features_ready_at_a_content_keyed_path(store_with_rgbn):
    store, ref = store_with_rgbn
    ctx = _Ctx(store)
    job = new_message("rgbn.ready", fragment="F7", face="front", artifact=ref)
    events = stage.handle(job, ctx)
    assert [e["type"] for e in events] == ["features.ready"]
    ev = validate(events[0])
    assert (ev["fragment"], ev["face"]) == ("F7", "front")
    assert ev["artifact"]["path"] == stage.output_path("F7", "front", ref.sha256)
    assert ev["artifact"]["path"].startswith("fragments/F7/features/front-")
    table = load_features(store, ev["artifact"])
    assert table.n_patches > 0 and (table.face, table.fragment) == ("front", "F7") and ctx.calls


def test_redelivered_job_finds_its_output_and_does_not_recompute(store_with_rgbn):
    store, ref = store_with_rgbn
    job = new_message("rgbn.ready", fragment="F7", face="front", artifact=ref)
    first = stage.handle(job, _Ctx(store))[0]["artifact"]
    ctx = _Ctx(store)
    again = stage.handle(job, ctx)[0]["artifact"]
    assert again == first and ctx.calls == []


def test_wrong_job_type_and_corrupt_input_are_refused(store_with_rgbn):
    store, ref = store_with_rgbn
    with pytest.raises(MessageError):
        stage.handle(new_message("fragment.ready", fragment="F7", artifact=ref), _Ctx(store))
    bad = dict(ref.to_dict(), sha256="0" * 64)
    with pytest.raises(ArtifactError):
        stage.handle(new_message("rgbn.ready", fragment="F7", face="front", artifact=bad), _Ctx(store))


def test_bad_work_pixel_setting_is_named(store_with_rgbn):
    store, ref = store_with_rgbn
    ctx = _Ctx(store)
    ctx.config = {"work_pixel_mm": "fine"}
    with pytest.raises(ValueError, match="services.features.work_pixel_mm"):
        stage.handle(new_message("rgbn.ready", fragment="F7", face="front", artifact=ref), ctx)
    assert stage.work_pixel_mm({}) == 0.1 and stage.work_pixel_mm({"work_pixel_mm": 0.2}) == 0.2


def test_cli_describes_a_store_fragment_and_writes_debug_pictures(store_with_rgbn, tmp_path, capsys):
    store, _ = store_with_rgbn
    dbg = tmp_path / "dbg"
    assert tessera(["features", "--store", str(store.root), "--fragment", "F7", "--debug-dir", str(dbg)]) == 0
    out = capsys.readouterr().out
    assert "features.ready" in out and "colour_mean_r" in out
    assert sorted(p.name for p in dbg.iterdir()) == ["front-erosion.png", "front-orientation.png", "front-patches.png"]


def test_cli_store_form_reads_the_work_grid_setting_as_the_worker_does(store_with_rgbn, tmp_path, capsys):
    # docs/features.md: the --store form runs the stage "as the worker does", whose
    # [services.features] work_pixel_mm sets the grid (150 dpi: 0.4 mm -> 2 x 0.169 mm)
    store, _ = store_with_rgbn
    assert tessera(["features", "--store", str(store.root), "--fragment", "F7",
                    "--set", "services.features.work_pixel_mm=0.4"]) == 0
    assert "work grid 0.339 mm" in capsys.readouterr().out
    config = tmp_path / "station.toml"
    config.write_text("[services.features]\nwork_pixel_mm = 5.0\n")
    assert tessera(["features", "--store", str(store.root), "--fragment", "F7", "--config", str(config)]) == 1
    assert "services.features.work_pixel_mm" in capsys.readouterr().err
    # the default grid keeps its path; another one is a table of its own
    assert tessera(["features", "--store", str(store.root), "--fragment", "F7"]) == 0
    assert "work grid 0.169 mm" in capsys.readouterr().out
    assert len(list(store.path("fragments/F7/features").glob("front-*.h5"))) == 2


def test_cli_on_an_rgbn_file_writes_the_table(store_with_rgbn, tmp_path, capsys):
    store, ref = store_with_rgbn
    out = tmp_path / "t.h5"
    assert tessera(["features", str(store.path(ref.path)), "--out", str(out), "--json"]) == 0
    assert '"colour_mean_r"' in capsys.readouterr().out
    assert load_features(Store(tmp_path), "t.h5").values["colour_mean_r"] == pytest.approx(0.4, rel=1e-5)


def test_cli_json_stdout_is_only_the_json(store_with_rgbn, tmp_path, capsys):
    # `tessera features ... --json | python3 -m json.tool`: the event and the "wrote" lines go to stderr
    store, ref = store_with_rgbn
    assert tessera(["features", "--store", str(store.root), "--fragment", "F7", "--json",
                    "--debug-dir", str(tmp_path / "dbg")]) == 0
    cap = capsys.readouterr()
    assert json.loads(cap.out)["colour_mean_r"] == pytest.approx(0.4, rel=1e-5)
    assert "features.ready" in cap.err and "wrote" in cap.err
    assert tessera(["features", str(store.path(ref.path)), "--out", str(tmp_path / "t.h5"), "--json"]) == 0
    cap = capsys.readouterr()
    assert "colour_mean_r" in json.loads(cap.out) and "wrote" in cap.err


def test_cli_reports_a_missing_fragment_plainly(tmp_path, capsys):
    assert tessera(["features", "--store", str(tmp_path), "--fragment", "NOPE"]) == 1
    assert "no RGBN artifact" in capsys.readouterr().err
    assert tessera(["features"]) == 2


def _strict_json(text: str):
    """Parse as ``jq`` or a browser does: a bare NaN / Infinity is an error, not a number."""
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_cli_json_writes_every_value_that_is_not_finite_as_null(store_with_rgbn, monkeypatch, capsys):
    # a ratio over an empty region can come out infinite: Python wrote it as `Infinity`, which is not JSON
    import common.features as features
    real = features.extract_features

    def with_undefined_values(image, face):
        table = real(image, face=face)
        table.values.update(colour_mean_g=float("inf"), colour_mean_b=float("-inf"), normal_z_mean=float("nan"))
        return table

    monkeypatch.setattr(features, "extract_features", with_undefined_values)
    store, ref = store_with_rgbn
    assert tessera(["features", str(store.path(ref.path)), "--json"]) == 0
    values = _strict_json(capsys.readouterr().out)
    assert values["colour_mean_g"] is None and values["colour_mean_b"] is None and values["normal_z_mean"] is None
    assert values["colour_mean_r"] == pytest.approx(0.4, rel=1e-5)   # the finite ones are kept
