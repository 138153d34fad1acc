"""Tests of common/web/tiles.py: the pyramid is an exact area average of the face, cut once."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from common.rgbn.image import RGBNImage, save_rgbn
from common.rgbn.io import linear_to_srgb
from common.store import Store
from common.web import tiles


def _face(h=300, w=410, seed=3):
    """A face with smooth random albedo, tilted normals and an irregular (elliptic) mask."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = np.clip(rng.random((h, w, 3), dtype=np.float32) * 0.6 + 0.2, 0, 1)
    nx, ny = 0.4 * np.sin(xx / 17.0), 0.3 * np.cos(yy / 11.0)
    normals = np.stack([nx, ny, np.ones_like(nx)], axis=2)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    mask = ((yy - h / 2) / (0.45 * h)) ** 2 + ((xx - w / 2) / (0.47 * w)) ** 2 < 1
    return RGBNImage(albedo, mask, 200.0, normals=normals.astype(np.float32))


def _block_sum(a, f):
    """Sum over f x f cells, zero-padding the edges: the independent expectation of a level."""
    h, w = a.shape[:2]
    a = np.pad(a.astype(np.float64), ((0, -h % f), (0, -w % f)) + ((0, 0),) * (a.ndim - 2))
    return a.reshape(a.shape[0] // f, f, a.shape[1] // f, f, *a.shape[2:]).sum(axis=(1, 3))


def _expected(img, level):
    f = 2 ** level
    m = img.mask.astype(np.float64)
    msum, count = _block_sum(m, f), _block_sum(np.ones_like(m), f)
    on = msum > 0
    alb = _block_sum(img.albedo * m[..., None], f) / np.maximum(msum, 1e-12)[..., None]
    n = _block_sum(img.normals * m[..., None], f)
    n /= np.maximum(np.linalg.norm(n, axis=2, keepdims=True), 1e-12)
    srgb = np.where(on[..., None], np.round(linear_to_srgb(alb.astype(np.float32)) * 255), 0)
    nrgb = np.where(on[..., None], np.round((n + 1) / 2 * 255), 128)   # 128: "no normal" off the fragment
    alpha = np.round(msum / count * 255)
    return srgb, nrgb, alpha


@pytest.fixture
def cut(tmp_path):
    store = Store(tmp_path)
    img = _face()
    rel = "fragments/F1/rgbn/front-0123456789abcdef.h5"
    save_rgbn(store, rel, img)
    info = tiles.cut_source(store, rel, tile_px=64)
    return store, img, rel, info


def test_pyramid_levels_halve_rounding_up_until_one_tile():
    assert tiles.pyramid_levels(600, 1000) == [(600, 1000), (300, 500), (150, 250)]
    assert tiles.pyramid_levels(256, 256) == [(256, 256)]
    assert tiles.pyramid_levels(257, 3) == [(257, 3), (129, 2)]
    with pytest.raises(ValueError, match="height and width"):
        tiles.pyramid_levels(0, 10)
    # a pyramid can go on below one tile (the relight pyramid's small first picture)
    assert tiles.pyramid_levels(600, 1000, top_px=64) == [(600, 1000), (300, 500), (150, 250), (75, 125), (38, 63)]
    assert tiles.pyramid_levels(40, 30, top_px=64) == [(40, 30)]
    with pytest.raises(ValueError, match="top_px"):
        tiles.pyramid_levels(600, 1000, top_px=512)


def test_every_level_is_the_masked_area_average_of_the_face(cut):
    store, img, rel, info = cut
    cache = tiles.TileCache(store)
    assert [(lv["height"], lv["width"]) for lv in info["levels"]] == tiles.pyramid_levels(300, 410, 64)
    assert set(info["layers"]) == {"albedo", "normals"}
    for lv in info["levels"]:
        level, h, w = lv["level"], lv["height"], lv["width"]
        srgb, nrgb, alpha = _expected(img, level)
        got_a = cache.region(rel, "albedo", level, 0, h, 0, w)
        got_n = cache.region(rel, "normals", level, 0, h, 0, w)
        # float32 sums in another order than the float64 expectation: at most one step of 8 bits
        assert np.abs(got_a[..., :3].astype(int) - srgb).max() <= 1, level
        assert np.abs(got_n[..., :3].astype(int) - nrgb).max() <= 1, level
        assert np.abs(got_a[..., 3].astype(int) - alpha).max() <= 1, level
        assert np.array_equal(got_a[..., 3], got_n[..., 3])
    # level 0 is the face itself: alpha is the mask, RGB the display sRGB of the albedo
    lvl0 = cache.region(rel, "albedo", 0, 0, 300, 0, 410)
    assert np.array_equal(lvl0[..., 3] == 255, img.mask) and set(np.unique(lvl0[..., 3])) == {0, 255}
    # OpenGL convention: a normal leaning up (+y) has green above 128
    up = cache.region(rel, "normals", 0, 150, 151, 205, 206)[0, 0]
    assert (up[1] > 128) == (img.normals[150, 205, 1] > 0)


def test_tiles_are_256_px_pngs_at_the_documented_path(tmp_path):
    store = Store(tmp_path)
    img = _face(300, 600)
    rel = "fragments/F2/rgbn/back-00000000000000aa.h5"
    save_rgbn(store, rel, img)
    info = tiles.TileCache(store).pyramid(rel)
    folder = store.path(tiles.pyramid_folder(rel))
    assert folder.name == f"rgbn-back-00000000000000aa-t{tiles.TILES_VERSION}"
    assert info["tile_px"] == 256 and info["levels"][0]["cols"] == 3 and info["levels"][0]["rows"] == 2
    t = tiles.decode_png((folder / "albedo/0/2_1.png").read_bytes())
    assert t.shape == (300 - 256, 600 - 512, 4)   # the last tile of a level is cut to the image
    assert tiles.decode_png((folder / "albedo/0/0_0.png").read_bytes()).shape == (256, 256, 4)
    assert info["source"]["sha256"] == store.ref(rel).sha256 and info["tiles"] == 2 * (6 + 2 + 1)
    assert json.loads((folder / "pyramid.json").read_text()) == info


def test_the_pyramid_is_cut_once_and_an_interrupted_cut_is_redone_identically(cut):
    store, img, rel, info = cut
    folder = store.path(tiles.pyramid_folder(rel))
    tile = folder / "normals/1/2_1.png"
    before, stamp = tile.read_bytes(), tile.stat().st_mtime_ns
    assert tiles.TileCache(store).pyramid(rel) == info   # read, not cut again
    assert tile.stat().st_mtime_ns == stamp
    (folder / "pyramid.json").unlink()                  # a cut killed before its last file
    tile.unlink()
    again = tiles.TileCache(store, tile_px=64).pyramid(rel)
    assert tile.read_bytes() == before and again["levels"] == info["levels"]
    assert not list(folder.rglob("*.tmp"))


def test_tile_lookups_outside_the_pyramid_say_what_is_wrong(cut):
    store, img, rel, info = cut
    cache = tiles.TileCache(store)
    with pytest.raises(LookupError, match="no layer 'render'"):
        cache.tile_path(rel, "render", 0, 0, 0)
    with pytest.raises(LookupError, match="level must be"):
        cache.tile_path(rel, "albedo", 99, 0, 0)
    with pytest.raises(LookupError, match="outside level 0"):
        cache.tile_path(rel, "albedo", 0, 7, 0)
    with pytest.raises(ValueError, match="not an RGBN or render artifact"):
        tiles.pyramid_folder("fragments/F1/features/front-1.h5")


def test_a_colour_only_face_has_no_normals_layer_and_a_render_its_own_pyramid(tmp_path):
    store = Store(tmp_path)
    img = _face(100, 120)
    save_rgbn(store, "fragments/F3/rgbn/front-1111111111111111.h5",
              RGBNImage(img.albedo, img.mask, img.dpi))
    info = tiles.cut_source(store, "fragments/F3/rgbn/front-1111111111111111.h5")
    assert list(info["layers"]) == ["albedo"]

    drawn = (np.arange(100 * 120 * 3).reshape(100, 120, 3) % 251).astype(np.uint8)
    alpha = np.where(img.mask, 255, 0).astype(np.uint8)

    def fill(f):
        f.create_dataset("image", data=drawn)
        f.create_dataset("alpha", data=alpha)
        f.attrs.update(recipe="toon", bits=8, dpi=200.0)

    rrel = "fragments/F3/renders/front-2222222222222222.h5"
    store.write(rrel, "tessera.render", 1, fill,
                provenance={"inputs": [{"path": "fragments/F3/rgbn/front-1111111111111111.h5"}]})
    rinfo = tiles.cut_source(store, rrel)
    assert list(rinfo["layers"]) == ["render"] and rinfo["kind"] == "render"
    got = tiles.TileCache(store).region(rrel, "render", 0, 0, 100, 0, 120)
    assert np.array_equal(got[..., :3][img.mask], drawn[img.mask]) and np.array_equal(got[..., 3], alpha)
    assert tiles.face_sources(store, "F3") == {"front": {"rgbn": "fragments/F3/rgbn/front-1111111111111111.h5",
                                                         "normals": False, "renders": {"toon": rrel}}}


def test_the_tile_list_offers_only_the_layers_a_colour_only_face_has(tmp_path):
    """The tile list offered a ``normals`` layer for every face, and a colour-only face (an imported picture)
    then answered 404 on it: the list names only the layers a face has, and the 404 says why."""
    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    img = _face(60, 80)
    save_rgbn(store, "fragments/C1/rgbn/front-00000000000000dd.h5", RGBNImage(img.albedo, img.mask, img.dpi))
    save_rgbn(store, "fragments/C1/rgbn/back-00000000000000ee.h5", img)   # this face has normals
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    faces = c.get("/api/tiles/C1").json["faces"]
    assert list(faces["front"]["layers"]) == ["albedo"]
    assert list(faces["back"]["layers"]) == ["albedo", "normals"]
    for face in faces.values():   # every layer listed is there
        for url in face["layers"].values():
            assert c.get(url).status_code == 200, url
    r = c.get("/api/tiles/C1/front/normals")
    assert r.status_code == 404 and "colour-only" in r.json["error"] and "layers: albedo" in r.json["error"]
    assert c.get("/dzi/C1~front~normals.dzi").status_code == 404
    assert c.get("/iiif/image/C1~front~normals/info.json").status_code == 404


def test_cut_pyramid_checks_its_bands():
    with pytest.raises(ValueError, match="held 10 rows, expected 20"):
        tiles.cut_pyramid(iter([np.zeros((10, 5, 5), np.float32)]), 20, 5, {"albedo": 0}, lambda *a: None)
    with pytest.raises(ValueError, match=r"bands must be \(rows, 5, C\)"):
        tiles.cut_pyramid(iter([np.zeros((10, 4, 5), np.float32)]), 10, 5, {"albedo": 0}, lambda *a: None)


# -- the tile API of the web app (services/web/tiles.py) ---------------------------------------

def test_the_tile_api_lists_faces_serves_pyramids_and_immutable_tiles(tmp_path):
    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    img = _face(300, 600)
    rel = "fragments/F4/rgbn/front-00000000000000bb.h5"
    save_rgbn(store, rel, img)
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    listing = c.get("/api/tiles/F4").json
    assert listing["faces"]["front"]["source"] == rel
    assert listing["faces"]["front"]["layers"]["normals"] == "/api/tiles/F4/front/normals"
    info = c.get("/api/tiles/F4/front/normals").json
    assert info["tiles"] == "/api/tiles/F4/rgbn-front-00000000000000bb-t1/normals/{level}/{col}_{row}.png"
    assert info["width"] == 600 and info["height"] == 300 and info["levels"][-1]["cols"] == 1
    r = c.get(info["tiles"].format(level=0, col=1, row=0))
    assert r.status_code == 200 and r.headers["Content-Type"] == "image/png"
    assert "immutable" in r.headers["Cache-Control"]
    got = tiles.decode_png(r.data)
    want = tiles.TileCache(store).region(rel, "normals", 0, 0, 256, 256, 512)
    assert got.shape == (256, 256, 4) and np.array_equal(got, want)
    # what is not there is a 404 (JSON) naming it; a bad id a 400
    assert "outside level 0" in c.get(info["tiles"].format(level=0, col=9, row=0)).json["error"]
    assert "no face 'back'" in c.get("/api/tiles/F4/back/albedo").json["error"]
    assert "no layer 'render-toon'" in c.get("/api/tiles/F4/front/render-toon").json["error"]
    assert c.get("/api/tiles/F5").status_code == 404
    assert c.get("/api/tiles/F4/rgbn-front-00000000000000cc-t1/albedo/0/0_0.png").status_code == 404
    assert c.get("/api/tiles/..%2Fx").status_code in (400, 404)


def test_deep_zoom_serves_the_same_pyramid_counted_from_the_1px_level(tmp_path):
    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    img = _face(300, 600)
    rel = "fragments/F6/rgbn/front-00000000000000dd.h5"
    save_rgbn(store, rel, img)
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    r = c.get("/dzi/F6~front~normals.dzi")
    assert r.status_code == 200 and 'TileSize="256"' in r.text and '<Size Width="600" Height="300"/>' in r.text
    assert tiles.dzi_max_level(600, 300) == 10 and tiles.dzi_max_level(256, 1) == 8 and tiles.dzi_max_level(1, 1) == 0
    cache = tiles.TileCache(store)
    full = tiles.decode_png(c.get("/dzi/F6~front~normals_files/10/1_0.png").data)
    assert np.array_equal(full, cache.region(rel, "normals", 0, 0, 256, 256, 512))
    top = tiles.decode_png(c.get("/dzi/F6~front~albedo_files/8/0_0.png").data)      # pyramid level 2
    assert np.array_equal(top, cache.region(rel, "albedo", 2, 0, 75, 0, 150))
    tiny = tiles.decode_png(c.get("/dzi/F6~front~albedo_files/0/0_0.png").data)     # below the pyramid
    assert tiny.shape == (1, 1, 4)
    assert c.get("/dzi/F6~front~albedo_files/11/0_0.png").status_code == 404
    assert c.get("/dzi/F6~front~albedo_files/3/1_0.png").status_code == 404


def test_downloads_are_the_export_files_cut_once_and_zipped(tmp_path):
    import io
    import zipfile

    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    img = _face(60, 80)
    save_rgbn(store, "fragments/F9/rgbn/front-0000000000000099.h5", img)
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    d = c.get("/api/downloads/F9").json
    names = [f["name"] for f in d["files"]]
    assert names == ["front-albedo.png", "front-normals.png", "metadata.json"]
    r = c.get(d["files"][1]["url"])
    assert r.status_code == 200 and "attachment" in r.headers["Content-Disposition"]
    normals = cv2.imdecode(np.frombuffer(r.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert normals.dtype == np.uint16 and normals.shape == (60, 80, 4)   # tessera export's 16-bit OpenGL map
    z = zipfile.ZipFile(io.BytesIO(c.get(d["zip"]).data))
    assert sorted(z.namelist()) == [f"F9/{n}" for n in names]
    assert c.get("/api/downloads/F9").json["key"] == d["key"]          # exported once
    assert c.get(f"/api/downloads/F9/{'0' * 16}/metadata.json").status_code == 404
    assert c.get(f"/api/downloads/F9/{d['key']}/..%2Fx").status_code == 404
    assert c.get("/api/downloads/F10").status_code == 404


def test_tessera_web_cut_tiles_cuts_every_pyramid_and_names_a_missing_fragment(tmp_path, capsys):
    from services.cli import main

    store = Store(tmp_path)
    save_rgbn(store, "fragments/C1/rgbn/front-00000000000000c1.h5", _face(40, 60))
    save_rgbn(store, "fragments/C2/rgbn/back-00000000000000c2.h5", _face(50, 30))
    assert main(["web", "--cut-tiles", "--set", f"storage.root={tmp_path}"]) == 0
    for rel in ("fragments/C1/rgbn/front-00000000000000c1.h5", "fragments/C2/rgbn/back-00000000000000c2.h5"):
        assert store.path(tiles.pyramid_folder(rel) + "/pyramid.json").is_file()
    assert "2 pyramids ready" in capsys.readouterr().out
    assert main(["web", "--cut-tiles", "C9", "--set", f"storage.root={tmp_path}"]) == 2
    assert "no face on storage for C9" in capsys.readouterr().out


def test_a_face_that_cannot_be_read_is_a_clear_error(tmp_path):
    from services import web
    from tests.web.conftest import TOKEN

    bad = tmp_path / "fragments/B1/rgbn/front-0000000000000bad.h5"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not an HDF5 file")
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    for url in ("/api/tiles/B1/front/albedo", "/iiif/image/B1~front~albedo/info.json", "/dzi/B1~front~albedo.dzi"):
        r = c.get(url)
        assert r.status_code == 500 and "cannot be read" in r.json["error"], url


def test_a_download_on_full_storage_says_so_and_leaves_nothing_half_written(tmp_path, monkeypatch):
    """An export writing onto a full disk raised a bare OSError (a 500 without a word) and left its temporary
    folder; now the storage's refusal is said (507, "storage full") and the folder is gone."""
    import errno

    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    save_rgbn(store, "fragments/F9/rgbn/front-0000000000000099.h5", _face(60, 80))

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("common.imports.export._write_folder", full)   # the disk fills up while the files are written
    r = web.create_app(token=TOKEN, store_root=tmp_path).test_client().get("/api/downloads/F9")
    assert r.status_code == 507 and "storage full" in r.json["error"]
    assert not list(store.root.rglob(".F9.*.tmp"))


def test_a_download_is_refused_before_writing_when_the_storage_lacks_the_room(tmp_path, monkeypatch):
    """The export of a download and its zip check the storage's free space against the files' sizes plus a
    margin before writing anything (507 naming the bytes needed and free); with the room they are written."""
    import collections
    import shutil

    from services import web
    from tests.web.conftest import TOKEN

    store = Store(tmp_path)
    save_rgbn(store, "fragments/F9/rgbn/front-0000000000000099.h5", _face(60, 80))
    usage = collections.namedtuple("usage", "total used free")
    free = {"bytes": 1000}
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 ** 12, 10 ** 12 - free["bytes"], free["bytes"]))
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    r = c.get("/api/downloads/F9")
    assert r.status_code == 507 and "storage full" in r.json["error"]
    assert "the export of F9" in r.json["error"] and "1000 free" in r.json["error"]
    assert not store.path("fragments/F9/downloads").exists() or not any(store.path("fragments/F9/downloads").rglob("*.*"))
    free["bytes"] = 10 ** 9
    d = c.get("/api/downloads/F9").json
    folder = store.path(f"fragments/F9/downloads/{d['key']}/F9")
    files = sum(p.stat().st_size for p in folder.iterdir())
    free["bytes"] = files        # the files fit once, but not with the zip's headers and the margin
    r = c.get(d["zip"])
    assert r.status_code == 507 and "needs " in r.json["error"] and f"{files} free" in r.json["error"]
    assert not (folder.parent / "F9.zip").exists() and not list(folder.parent.glob(".F9.zip.*"))
    free["bytes"] = 10 ** 9
    assert c.get(d["zip"]).status_code == 200


def test_face_sources_refuses_faces_and_renders_of_a_newer_schema_version(tmp_path, caplog):
    """docs/storage.md: every reader opens a file with its schema and the highest version it understands
    and refuses a newer one. face_sources read a face's normals and a render's provenance and recipe with a
    plain h5py.File, so a face written by a newer Tessera offered a normals layer and its renders."""
    from common.render.artifact import SCHEMA as RENDER, SCHEMA_VERSION as RENDER_VERSION
    from common.rgbn.image import SCHEMA as RGBN, SCHEMA_VERSION as RGBN_VERSION

    store = Store(tmp_path)
    rel = "fragments/N2/rgbn/front-00000000000000aa.h5"

    def face(f):
        f.create_dataset("mask", data=np.ones((30, 40), bool))
        f.create_dataset("normals", data=np.zeros((30, 40, 3), np.float32))
        f.attrs.update(dpi=300.0)

    store.write(rel, RGBN, RGBN_VERSION + 1, face)

    def render(recipe):
        def fill(f):
            f.create_dataset("image", data=np.zeros((30, 40, 3), np.uint8))
            f.create_dataset("alpha", data=np.zeros((30, 40), np.uint8))
            f.attrs.update(recipe=recipe, bits=8, dpi=300.0)
        return fill

    old = "fragments/N2/renders/front-1111111111111111.h5"
    new = "fragments/N2/renders/front-2222222222222222.h5"
    store.write(old, RENDER, RENDER_VERSION, render("toon"), provenance={"inputs": [{"path": rel}]})
    store.write(new, RENDER, RENDER_VERSION + 1, render("ink"), provenance={"inputs": [{"path": rel}]})
    assert tiles.face_sources(store, "N2") == {"front": {"rgbn": rel, "normals": False, "renders": {"toon": old}}}
    assert f"{rel} ({RGBN}) has schema version {RGBN_VERSION + 1}" in caplog.text
    assert f"{new} ({RENDER}) has schema version {RENDER_VERSION + 1}" in caplog.text
