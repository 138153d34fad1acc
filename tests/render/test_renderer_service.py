import logging

import numpy as np
import pytest

from common.messages import MessageError, new_message, validate
from common.render.artifact import load_rendering
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from services import renderer
from tests.rgbn.analytic import sphere


class Ctx:
    def __init__(self, store, config=None):
        self.store = store
        self.config = config or {}
        self.log = logging.getLogger("test.renderer")
        self.progress_seen = []

    def progress(self, fraction, text):
        self.progress_seen.append(fraction)


@pytest.fixture
def rgbn_job(tmp_path):
    store = Store(tmp_path / "store")
    n, mask = sphere(48, 2.0, 0.1)
    img = RGBNImage(albedo=np.full((48, 48, 3), 0.6), mask=mask, dpi=254.0, normals=n)
    ref = save_rgbn(store, "fragments/F1/rgbn/front-abc.h5", img)
    return store, new_message("rgbn.ready", fragment="F1", face="front", artifact=ref)


def test_rgbn_ready_is_rendered_with_the_configured_recipe_on_the_same_grid(rgbn_job):
    store, job = rgbn_job
    ctx = Ctx(store, {"recipe": "relief"})
    (event,) = renderer.handle(job, ctx)
    validate(event)
    assert event["type"] == "render.ready" and event["fragment"] == "F1" and event["recipe"] == "relief"
    assert event["artifact"]["path"].startswith("fragments/F1/renders/front-")
    image, alpha, attrs = load_rendering(store, event["artifact"])
    assert image.shape == (48, 48, 3) and alpha.shape == (48, 48)
    assert attrs["recipe"] == "relief" and attrs["bits"] == 8 and "exaggerated" in attrs["recipe_toml"]
    assert ctx.progress_seen and max(ctx.progress_seen) <= 1.0


def test_redelivered_job_finds_its_output_and_a_new_recipe_makes_a_new_one(rgbn_job):
    store, job = rgbn_job
    first = renderer.handle(job, Ctx(store))[0]
    again = renderer.handle(job, Ctx(store))[0]
    assert again["artifact"] == first["artifact"]
    other = renderer.handle(job, Ctx(store, {"recipe": "raking"}))[0]
    assert other["artifact"]["path"] != first["artifact"]["path"]
    _, _, attrs = load_rendering(store, other["artifact"])
    assert attrs["bits"] == 16


def test_wrong_event_type_is_refused(rgbn_job):
    store, job = rgbn_job
    with pytest.raises(MessageError, match="rgbn.ready"):
        renderer.handle(dict(job, type="features.ready"), Ctx(store))


def test_a_rendered_face_has_its_archive_tiles_cut_so_no_first_view_waits(tmp_path):
    from common.web.relight import RelightCache
    from common.web.tiles import pyramid_folder, pyramid_levels

    store = Store(tmp_path / "store")
    n, mask = sphere(300, 12.0, 0.1)   # 300 px: two pyramid levels of 256-px tiles
    img = RGBNImage(albedo=np.full((300, 300, 3), 0.6), mask=mask, dpi=254.0, normals=n)
    ref = save_rgbn(store, "fragments/F2/rgbn/front-abc.h5", img)
    job = new_message("rgbn.ready", fragment="F2", face="front", artifact=ref)
    (event,) = renderer.handle(job, Ctx(store))
    for source in (ref.path, event["artifact"]["path"]):
        assert store.path(f"{pyramid_folder(source)}/pyramid.json").is_file()
    # the relight tiles of every level but full resolution: level 1 is 150 x 150, one tile
    assert pyramid_levels(300, 300) == [(300, 300), (150, 150)]
    relight = RelightCache(store, ref.path)
    assert store.path(relight.tile_relpath(1, 0, 0)).is_file()
    assert not store.path(relight.tile_relpath(0, 0, 0)).is_file()   # level 0 is cut on demand


def test_archive_tiles_can_be_left_to_the_first_view(rgbn_job):
    store, job = rgbn_job
    renderer.handle(job, Ctx(store, {"archive_tiles": False}))
    assert not (store.root / "fragments" / "F1" / "tiles").exists()
    assert not (store.root / "fragments" / "F1" / "viewer").exists()


@pytest.mark.parametrize("side", [48, 260])   # read whole, and drawn tile by tile (render_h5's H5Source)
def test_a_colour_only_face_is_reported_once_naming_the_fragment_and_face(tmp_path, caplog, monkeypatch, side):
    """The styles a colour-only face cannot have were warned about twice (the service, then the library per
    image or per tile, without saying which face): the service says it once, naming the fragment and face, at INFO
    (it was a WARNING for every imported picture, though colour-only imports are normal)."""
    import common.render.tiles as tiles

    monkeypatch.setattr(tiles, "TILE_MPX", 0.02)   # 260 x 260 px is then drawn in tiles
    store = Store(tmp_path / "store")
    img = RGBNImage(albedo=np.full((side, side, 3), 0.6), mask=np.ones((side, side), bool), dpi=254.0)
    ref = save_rgbn(store, "fragments/F2/rgbn/back-abc.h5", img)
    job = new_message("rgbn.ready", fragment="F2", face="back", artifact=ref)
    with caplog.at_level(logging.INFO):
        (event,) = renderer.handle(job, Ctx(store, {"recipe": "relief", "archive_tiles": False}))
    said = [(r.levelname, r.getMessage()) for r in caplog.records if "no normals" in r.getMessage()]
    # at INFO: colour-only imports are normal, not a fault (a WARNING for every imported picture was noise)
    assert said == [("INFO", "fragment F2 back has no normals: skipped exaggerated, ridges_valleys")]
    assert load_rendering(store, event["artifact"])[2]["skipped_styles"] == "exaggerated,ridges_valleys"
