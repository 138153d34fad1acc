"""The fragment page (``/fragments/<id>``): its relighting fields and tiles, its JSON, and the page
itself in Chromium (first picture, relighting, deep zoom, measuring in mm, joins).

Screenshots go to a temporary folder, or to ``docs/web/`` with ``TESSERA_WEB_SCREENSHOTS=1``.
"""

from __future__ import annotations

import gzip
import json
import math
import os
import re

import numpy as np
import pytest

from .conftest import TOKEN
from .viewer_support import CHROMIUM, CHROMIUM_ARGS, REPO, WebProcess, open_viewer, relief_face, require_browser, \
    screenshot, show_one_to_one, wait_complete


def _store_with(tmp_path, image, fid="F-1", stem="front-k1"):
    from common.rgbn.image import save_rgbn
    from common.store import Store

    store = Store(tmp_path / "storage")
    save_rgbn(store, f"fragments/{fid}/rgbn/{stem}.h5", image)
    return store


# ---- the fields and tiles ------------------------------------------------------------------------

def test_level0_tile_holds_the_whole_image_fields(tmp_path):
    """A level-0 tile cut with its halo holds what smoothing / curvature of the whole face give there."""
    from common.rgbn.curvature import mean_curvature
    from common.rgbn.smoothing import smooth_normals
    from common.web.relight import RelightCache, unpack_tile

    image = relief_face(200, 300)
    store = _store_with(tmp_path, image)
    cache = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    p = cache.params()
    assert p["levels"][0] == [300, 200] and p["levels"][-1][0] <= 256
    data = cache.tile_path(0, 0, 1).read_bytes()
    xy, H, colour = unpack_tile(data, 200, 300 - 256)
    cols = slice(256, 300)
    for k, sigma in enumerate([0.0] + p["exaggerated_sigmas_px"] + [p["unsharp_sigma_px"]]):
        want = smooth_normals(image.normals, sigma, mask=image.mask)[:, cols, :2] if sigma else image.normals[:, cols, :2]
        got = xy[..., 2 * k:2 * k + 2]
        assert np.abs(got - want)[image.mask[:, cols]].max() < 2e-3, f"field {k} (sigma {sigma})"
    want_H = mean_curvature(image.normals, image.dpi, mask=image.mask, sigma_px=p["curvature_sigma_px"])[:, cols]
    assert np.abs(H - want_H).max() <= 2e-3 * max(1.0, np.abs(want_H).max())
    assert (colour[..., 3] == np.where(image.mask[:, cols], 255, 0)).all()


def test_coarse_level_is_the_masked_area_average(tmp_path):
    from common.web.relight import read_level_window

    image = relief_face(64, 96)
    store = _store_with(tmp_path, image)
    with store.open("fragments/F-1/rgbn/front-k1.h5") as f:
        alb, nrm, mask = read_level_window(f, 2, 0, 16, 0, 24)
    m = image.mask.reshape(16, 4, 24, 4).astype(np.float64)
    cover = m.mean(axis=(1, 3))
    assert (mask == (cover >= 0.5)).all()
    a = (image.albedo.reshape(16, 4, 24, 4, 3) * m[..., None]).sum(axis=(1, 3)) / np.maximum(m.sum(axis=(1, 3)), 1e-12)[..., None]
    n = (image.normals.reshape(16, 4, 24, 4, 3) * m[..., None]).sum(axis=(1, 3))
    n /= np.linalg.norm(n, axis=2, keepdims=True).clip(1e-12)
    assert np.abs(alb - a)[cover > 0].max() < 1e-5
    assert np.abs(nrm - n)[cover > 0].max() < 1e-5


def test_tiles_are_cut_once_and_kept(tmp_path):
    from common.web.relight import RelightCache

    store = _store_with(tmp_path, relief_face(100, 300))      # level 0: 2 tiles, levels 1-3 (150, 75, 38 px): 1
    cache = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    path = cache.tile_path(0, 0, 0)
    stamp = path.stat().st_mtime_ns
    assert cache.tile_path(0, 0, 0).stat().st_mtime_ns == stamp
    assert path.is_relative_to(store.root / "fragments/F-1/viewer")
    assert not list(path.parent.glob(".*.tmp"))
    with pytest.raises(ValueError, match="outside level 0"):
        cache.tile_path(0, 3, 0)
    # cutting ahead of a view: every tile of every level once, the one already there kept
    seen = []
    assert cache.cut(min_level=0, progress=lambda done, total: seen.append((done, total))) == 5
    assert seen == [(k, 5) for k in range(1, 6)] and path.stat().st_mtime_ns == stamp
    assert len(list((store.root / cache.folder).rglob("*.bin.gz"))) == 5


def test_cut_in_one_pass_gives_the_tiles_a_view_asks_for(tmp_path):
    """Coarse levels cut whole from one read of the face hold what tile-by-tile cutting gives."""
    from common.web.relight import RelightCache, unpack_tile

    store = _store_with(tmp_path, relief_face(600, 700))       # levels 700x600, 350x300, 175x150, 88x75, 44x38
    on_demand = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    ahead = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    ahead.folder += "-ahead"
    assert ahead.cut(min_level=1) == 2 * 2 + 1 + 1 + 1
    for level, (r, c), (h, w) in ((1, (1, 1), (300 - 256, 350 - 256)), (1, (0, 0), (256, 256)), (2, (0, 0), (150, 175))):
        a = unpack_tile(on_demand.tile_path(level, r, c).read_bytes(), h, w)
        b = unpack_tile(ahead.tile_path(level, r, c).read_bytes(), h, w)
        assert (a[2] == b[2]).all()
        on = a[2][..., 3] > 0       # off the fragment the smoothed fields are extrapolations, never drawn
        assert np.abs(a[0] - b[0])[on].max() < 2e-3
        assert np.abs(a[1] - b[1])[on].max() < 2e-3 * max(1.0, np.abs(a[1]).max())


def test_level_image_from_tiles_is_the_level(tmp_path):
    """What "auto" contrast measures: a level assembled from its tiles equals the level read from the face."""
    from common.web.relight import RelightCache, read_level_window

    store = _store_with(tmp_path, relief_face(300, 560))
    cache = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    image = cache.level_image(1)
    with store.open("fragments/F-1/rgbn/front-k1.h5") as f:
        alb, nrm, mask = read_level_window(f, 1, 0, 150, 0, 280)
    assert image.dpi == 150.0 and image.mask.shape == (150, 280) and (image.mask == mask).all()
    assert np.abs(image.normals - nrm)[mask].max() < 2e-3
    assert np.abs(image.albedo - alb)[mask].max() < 0.01      # 8-bit sRGB


def test_colour_only_face_has_flat_fields(tmp_path):
    from common.rgbn.image import RGBNImage
    from common.web.relight import RelightCache, unpack_tile

    face = relief_face(40, 50)
    store = _store_with(tmp_path, RGBNImage(albedo=face.albedo, mask=face.mask, dpi=300.0))
    cache = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5")
    assert cache.params()["has_normals"] is False
    xy, H, colour = unpack_tile(cache.tile_path(0, 0, 0).read_bytes(), 40, 50)
    assert not xy.any() and not H.any() and (colour[..., 3] > 0).sum() == face.mask.sum()
    from services import web

    client = web.create_app(token=TOKEN, store_root=store.root).test_client()
    r = client.get("/api/fragments/F-1/relight/front-k1/auto?style=raking&values={}")
    assert r.status_code == 400 and "no normals" in r.get_json()["error"]
    r = client.get("/api/fragments/F-1/relight/front-k1/auto?style=albedo&values={}")
    assert r.status_code == 200 and len(r.get_json()["resolved"]["exposure"]) == 2


def test_offline_arguments_refuse_unknown_parameters():
    from common.web.relight import offline_arguments

    params = {"sigma_px": 1.0, "unsharp_sigma_mm": 1.0, "curvature_sigma_mm": 0.2}
    with pytest.raises(ValueError, match="raking has no parameter gain"):
        offline_arguments("raking", {"gain": 2.0}, params)
    with pytest.raises(ValueError, match="style must be one of"):
        offline_arguments("toon", {}, params)
    assert offline_arguments("raking", {}, params, level=1)["sigma_px"] == 0.5
    # what the fields were computed at wins over what a request asks (no costly scales from a URL)
    kw = offline_arguments("exaggerated", {"scales": 500, "sigma_ratio": 9.0}, params)
    assert (kw["scales"], kw["sigma_ratio"], kw["sigma0_px"]) == (3, 2.0, 1.0)


# ---- the JSON and the routes ---------------------------------------------------------------------

@pytest.fixture
def client(tmp_path):
    from common.matching.proposals import Proposal, ProposalStore
    from common.web.review import ReviewData
    from services import web

    store = _store_with(tmp_path, relief_face(60, 80))
    _store_with(tmp_path, relief_face(60, 80, seed=1), stem="back-k2")
    db = tmp_path / "storage" / "matches" / "proposals.sqlite"
    with ProposalStore(db) as s:
        s.upsert([Proposal("F-1", "F-2", 0.9, "m1", angle_deg=10.0, tx_mm=5.0, ty_mm=-2.0),
                  Proposal("F-1", "F-3", 0.4, "m1"), Proposal("F-1", "F-4", 0.6, "m1")])
        s.record_verdict("F-1", "F-2", "confirmed", by="ana")
        s.record_verdict("F-1", "F-4", "rejected", by="ana")
    app = web.create_app(token=TOKEN, store_root=store.root, review=ReviewData(db, store))
    return app.test_client()


def test_fragment_json_lists_faces_joins_and_proposals(client):
    r = client.get("/api/fragments/F-1")
    assert r.status_code == 200
    d = r.get_json()
    assert [f["face"] for f in d["faces"]] == ["front", "back"]
    assert d["faces"][0]["relight"] == "/api/fragments/F-1/relight/front-k1"
    assert [(j["other"], j["status"]) for j in d["joins"]] == [("F-2", "confirmed")]
    assert d["joins"][0]["other_url"] == "/fragments/F-2" and d["joins"][0]["pose"]["angle_deg"] == 10.0
    # docs/web.md: "the confirmed joins and the pending proposals" (a rejected pair was listed as a proposal)
    assert [(p["other"], p["status"]) for p in d["proposals"]] == [("F-3", "pending")]
    assert d["downloads"] == "/api/downloads/F-1"   # the archive's route for tessera export's files


def test_the_fragment_json_routes_answer_errors_in_json_like_the_archive(tmp_path):
    """docs/web.md, fragment page: the archive's JSON routes answer {"error": ...}, 404 for what is not there
    and 500 for a face on storage that cannot be read. These answered Flask's HTML pages, and an
    unreadable face was a 404 (params, tiles) or an HTML 500 (auto)."""
    from services import web

    bad = tmp_path / "fragments/B1/rgbn/front-0000000000000bad.h5"
    bad.parent.mkdir(parents=True)
    bad.write_bytes(b"not an HDF5 file")
    c = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    relight = "/api/fragments/B1/relight/front-0000000000000bad"
    for url in (f"{relight}/params.json", f"{relight}/tiles/0/0_0", f"{relight}/auto?style=albedo"):
        r = c.get(url)
        assert r.status_code == 500 and "cannot be read" in r.json["error"], url
    for url in ("/api/fragments/F-9", "/api/fragments/B1/relight/front-nope/params.json"):
        r = c.get(url)
        assert r.status_code == 404 and r.is_json and r.json["error"], url


def test_page_and_tile_routes(client):
    from services import web

    r = client.get("/fragments/F-1")
    assert r.status_code == 200 and b"viewer/viewer.js" in r.data and b"F-1" in r.data
    # the page carries every shader's source as it is on disk (no request of its own)
    block = re.search(r'<script type="application/json" id="viewer-shaders">(.*?)</script>', r.get_data(as_text=True), re.S)
    carried = json.loads(block.group(1))
    assert set(carried) == set(web.fragment.SHADER_FILES)
    for name in web.fragment.SHADER_FILES:
        assert carried[name] == (web.fragment.VIEWER_FOLDER / name).read_text(), name
    p = client.get("/api/fragments/F-1/relight/front-k1/params.json").get_json()
    assert p["width"] == 80 and p["height"] == 60 and p["dpi"] == 300.0
    t = client.get("/api/fragments/F-1/relight/front-k1/tiles/0/0_0")
    assert t.status_code == 200 and t.headers["Content-Encoding"] == "gzip"
    assert "immutable" in t.headers["Cache-Control"]
    assert len(gzip.decompress(t.data)) == 60 * 80 * (12 * 2 + 2 + 4)
    auto = client.get("/api/fragments/F-1/relight/front-k1/auto?style=raking&values=" + json.dumps({"colour": False}))
    lo, hi = auto.get_json()["resolved"]["exposure"]
    assert 0.0 <= lo < hi <= 1.0


def test_params_say_when_a_faces_dpi_is_nominal_and_how_it_faces(tmp_path):
    """A hand-held or RTI capture has no scale of its own (its provenance says dpi_nominal): the params say so, for
    the page to put beside every length; a scan's do not. They give the piece's extent (a scan cropped to what
    turned holds the lamp's shadow too: the page gives the piece's size, not the picture's). They carry the way a near-flat face faces
    (surface_normal, which the viewer lights it relative to). A params.json written before either was measured is
    measured again, and the tiles cut before are kept."""
    import json

    from common.rgbn.image import save_rgbn
    from common.web.relight import RelightCache
    from services import web

    store = _store_with(tmp_path, relief_face(60, 80))
    save_rgbn(store, "fragments/H-1/rgbn/front-k2.h5", relief_face(60, 80), provenance={"dpi_nominal": True})
    client = web.create_app(token=TOKEN, store_root=store.root).test_client()
    scan = client.get("/api/fragments/F-1/relight/front-k1/params.json").get_json()
    capture = client.get("/api/fragments/H-1/relight/front-k2/params.json").get_json()
    assert scan["dpi_nominal"] is False and capture["dpi_nominal"] is True
    mask = relief_face(60, 80).mask                           # the piece's extent: its mask's bounding box
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    assert scan["piece_px"] == [cols[0], rows[0], cols[-1] + 1, rows[-1] + 1] and (cols[0], rows[0]) != (0, 0)
    assert np.degrees(np.arccos(capture["surface_normal"][2])) < 5.0    # the analytic face is near-flat, square on
    cache = RelightCache(store, "fragments/H-1/rgbn/front-k2.h5")
    path = store.path(f"{cache.folder}/params.json")
    old = {k: v for k, v in json.loads(path.read_text()).items() if k not in ("dpi_nominal", "surface_normal", "piece_px")}
    path.write_text(json.dumps(old))
    tile = store.path(cache.tile_relpath(0, 0, 0))
    tile.parent.mkdir(parents=True, exist_ok=True)
    tile.write_bytes(b"a tile cut before")
    again = RelightCache(store, "fragments/H-1/rgbn/front-k2.h5").params()
    assert again["dpi_nominal"] is True and again["surface_normal"] == capture["surface_normal"]
    assert tile.read_bytes() == b"a tile cut before"


def test_opening_a_face_cuts_its_coarse_levels_in_one_background_pass(tmp_path):
    from common.web.relight import RelightCache
    from services import web
    from services.web import fragment

    store = _store_with(tmp_path, relief_face(100, 600), stem="front-k9")   # levels 600x100, 300x50, ..., 38x7
    app = web.create_app(token=TOKEN, store_root=store.root)
    assert app.test_client().get("/api/fragments/F-1/relight/front-k9/params.json").status_code == 200
    cache = RelightCache(store, "fragments/F-1/rgbn/front-k9.h5")
    assert fragment._cutting[cache.folder].wait(60)
    cut = sorted(p.relative_to(store.root / cache.folder).as_posix()
                 for p in (store.root / cache.folder).rglob("*.bin.gz"))
    # and on to the 64-px top level (38 x 7), the viewer's first picture
    assert cut == ["1/0_0.bin.gz", "1/0_1.bin.gz", "2/0_0.bin.gz", "3/0_0.bin.gz", "4/0_0.bin.gz"]


@pytest.mark.parametrize("url,code,words", [
    ("/fragments/bad id!", 400, "fragment"),
    ("/api/fragments/F-9", 404, "no RGBN face"),
    ("/api/fragments/F-1/relight/front-nope/params.json", 404, "front-nope"),
    ("/api/fragments/F-1/relight/front-k1/tiles/0/5_5", 404, "outside level 0"),
    ("/api/fragments/F-1/relight/front-k1/tiles/9/0_0", 404, "level must be"),
    ("/api/fragments/F-1/relight/front-k1/tiles/0/x", 404, "row"),
    ("/api/fragments/F-1/relight/front-k1/auto?style=raking&values=%7B%22gain%22%3A1%7D", 400, "no parameter gain"),
    ("/api/fragments/F-1/relight/front-k1/auto?style=raking&values=nope", 400, "JSON"),
])
def test_bad_requests_are_refused_with_a_reason(client, url, code, words):
    r = client.get(url)
    assert r.status_code == code
    assert words in r.get_data(as_text=True)


# ---- the page in Chromium ------------------------------------------------------------------------

@pytest.mark.slow
def test_fragment_page_in_chromium(tmp_path):
    """First picture, relighting by dragging, zoom to the level-0 tiles, a measurement in mm that
    matches the image's dpi, the scale bar, joins as links; every request goes to the station
    (OpenSeadragon's too), relighting uploads no texture, a face let go frees its textures."""
    require_browser()
    from playwright.sync_api import sync_playwright

    from common.matching.proposals import Proposal, ProposalStore

    shots = REPO / "docs" / "web" if os.environ.get("TESSERA_WEB_SCREENSHOTS") == "1" else tmp_path / "shots"
    shots.mkdir(parents=True, exist_ok=True)
    image = relief_face(1300, 2000, dpi=600.0)      # 85 x 55 mm at 600 dpi: four levels
    _store_with(tmp_path, image, fid="F-1", stem="front-k1")
    _store_with(tmp_path, relief_face(500, 700, dpi=600.0, seed=3), fid="F-1", stem="back-k3")
    _store_with(tmp_path, relief_face(300, 400, dpi=600.0, seed=2), fid="F-2", stem="front-k2")
    with ProposalStore(tmp_path / "storage" / "matches" / "proposals.sqlite") as s:
        s.upsert([Proposal("F-1", "F-2", 0.87, "m1", angle_deg=12.0, tx_mm=30.0, ty_mm=-4.0),
                  Proposal("F-1", "F-3", 0.35, "m1")])
        s.record_verdict("F-1", "F-2", "confirmed", by="ana")
    web = WebProcess(tmp_path).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 900}, bypass_csp=True)
            errors, requests = [], []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("request", lambda r: requests.append(r.url))
            open_viewer(page, f"{web.url}/fragments/F-1?face=front")
            first = page.evaluate("() => tesseraViewer.stats.firstTileMs")
            assert first is not None and page.evaluate("() => tesseraViewer.level()") >= 1
            # tessera export's files, from the archive's downloads (exported on this first request)
            page.wait_for_selector("#downloads a[href$='.zip']", timeout=120_000)
            names = page.locator("#downloads a").all_text_contents()
            assert {"front-albedo.png", "front-normals.png", "metadata.json"} <= set(names), names
            screenshot(page, shots / "fragment.png")

            # joins and proposals are links to the other fragments' pages
            assert page.locator("#joins a", has_text="F-2").get_attribute("href") == "/fragments/F-2"
            assert page.locator("#proposals a", has_text="F-3").count() == 1

            # drag in light mode: the light follows the pointer (RTIViewer's light sphere)
            box = page.locator("#gl").bounding_box()
            cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            r = min(box["width"], box["height"]) / 2
            page.mouse.move(cx, cy)
            page.mouse.down()
            page.mouse.move(cx - 0.5 * r, cy - 0.5 * r, steps=4)  # up-left, half-way to the rim
            page.mouse.up()
            az, el = page.evaluate("() => tesseraViewer.light")
            assert abs(az - 135.0) < 1.0 and abs(el - math.degrees(math.acos(math.sqrt(0.5)))) < 1.0
            assert page.input_value("#azimuth") == "135"

            # every style draws (the shaders compile and differ from each other)
            means = {}
            for style in ("albedo", "lambertian", "raking", "specular", "normal_unsharp", "exaggerated", "mean_curvature"):
                page.select_option("#style", style)
                means[style] = page.evaluate("""() => { tesseraViewer.render();
                    const c = tesseraViewer.canvas, px = tesseraViewer.pixels(0, 0, c.width, c.height);
                    let s = 0; for (let i = 0; i < px.length; i += 4) s += px[i] + px[i + 1] + px[i + 2];
                    return s / (px.length / 4 * 3); }""")
            assert len({round(m, 1) for m in means.values()}) == len(means), means
            # relighting is uniforms only: frames with another light upload no texture
            uploads = page.evaluate("() => tesseraViewer.stats.uploads")
            assert page.evaluate("() => tesseraViewer.frameTime(5)") > 0
            assert page.evaluate("() => tesseraViewer.stats.uploads") == uploads
            page.select_option("#style", "raking")
            screenshot(page, shots / "fragment-raking.png")

            # pan by dragging in pan mode, zoom with the wheel about the pointer
            page.click("button[data-mode=pan]")
            v0 = page.evaluate("() => ({...tesseraViewer.view})")
            dpr = page.evaluate("() => window.devicePixelRatio")
            page.mouse.move(cx, cy)
            page.mouse.down()
            page.mouse.move(cx + 100, cy + 50, steps=5)
            page.mouse.up()
            v1 = page.evaluate("() => ({...tesseraViewer.view})")
            assert abs((v0["cx"] - v1["cx"]) - 100 * dpr / v0["zoom"]) < 1e-6 * v0["cx"] + 1e-3
            assert abs((v0["cy"] - v1["cy"]) - 50 * dpr / v0["zoom"]) < 1e-6 * v0["cy"] + 1e-3
            under = page.evaluate(f"() => tesseraViewer.toImage({cx - box['x']} * {dpr}, {cy - box['y']} * {dpr})")
            page.mouse.move(cx, cy)
            page.mouse.wheel(0, -400)
            page.wait_for_function(f"() => tesseraViewer.view.zoom > {v1['zoom']} * 1.5")
            # (OpenSeadragon animates the zoom: wait until the view has arrived)
            page.wait_for_function("""() => { const a = tesseraViewer.view, b = tesseraViewer.currentView();
                return a.zoom === b.zoom && a.cx === b.cx && a.cy === b.cy; }""")
            after = page.evaluate(f"() => tesseraViewer.toImage({cx - box['x']} * {dpr}, {cy - box['y']} * {dpr})")
            # the point under the pointer stays (within the rounding of event coordinates to a CSS pixel)
            tol = dpr / v1["zoom"]
            assert abs(after[0] - under[0]) < tol and abs(after[1] - under[1]) < tol

            # deep zoom: 1:1 needs level 0, whose tiles arrive and are drawn
            show_one_to_one(page, 0, 0)
            assert page.evaluate("() => tesseraViewer.level()") == 0

            # measuring: a drag of known canvas length reads length / zoom / dpi in mm
            page.click("button[data-mode=measure]")
            zoom = page.evaluate("() => tesseraViewer.view.zoom")
            dpr = page.evaluate("() => window.devicePixelRatio")
            page.mouse.move(cx - 200, cy)
            page.mouse.down()
            page.mouse.move(cx + 100, cy + 400, steps=5)
            page.mouse.up()
            want_mm = math.hypot(300, 400) * dpr / zoom * 25.4 / 600.0
            got_mm = page.evaluate("() => tesseraViewer.measureMm()")
            assert abs(got_mm - want_mm) < 0.01, (got_mm, want_mm)
            assert page.text_content("#measure-readout") == f"{want_mm:.2f} mm"
            bar = page.evaluate("() => tesseraViewer.scaleBar()")
            assert abs(bar["px"] - bar["mm"] * 600.0 / 25.4 * zoom) < 1e-6 and 40 <= bar["px"] / dpr <= 130
            screenshot(page, shots / "fragment-measure.png")

            # the back: another face in the same canvas, the front's viewer let go with its textures
            page.evaluate("() => { window.front = tesseraViewer; }")
            assert page.evaluate("() => front.stats.gpuTiles") > 0
            page.click("#faces button[data-face=back]")
            page.wait_for_function("() => tesseraViewer.info.width === 700 && tesseraViewer.stats.complete")
            assert page.evaluate("() => front.stats.gpuTiles") == 0
            # the piece's size (its elliptic mask's extent), then the picture's (700 x 500 px at 600 dpi)
            back = relief_face(500, 700, dpi=600.0, seed=3).mask
            rows, cols = np.nonzero(back.any(axis=1))[0], np.nonzero(back.any(axis=0))[0]
            size = f"{(cols[-1] + 1 - cols[0]) / 600 * 25.4:.1f} × {(rows[-1] + 1 - rows[0]) / 600 * 25.4:.1f} mm"
            assert page.text_content("#face-info").startswith(f"{size} (picture 29.6 × 21.2 mm)")
            screenshot(page, shots / "fragment-back.png")
            page.click("#faces button[data-face=front]")
            page.wait_for_function("() => tesseraViewer.info.width === 2000 && tesseraViewer.stats.complete")

            # a one-face fragment offers one face; the join link opens the other fragment
            page.click("#joins a")
            open_viewer(page, page.url)
            assert page.locator("#faces button").count() == 1
            assert not errors, errors
            # nothing from outside the station: no CDN, and none of OpenSeadragon's default addresses
            outside = [u for u in requests if not u.startswith(web.url + "/")]
            assert requests and not outside, outside
            browser.close()
    finally:
        web.stop()


def test_fragment_page_keeps_to_its_content_security_policy(tmp_path):
    """Under the station's own CSP (no bypass) the page, OpenSeadragon included, breaks no rule: the
    one inline style OpenSeadragon adds is allowed by its hash and nothing else is inline."""
    require_browser()
    from playwright.sync_api import sync_playwright

    _store_with(tmp_path, relief_face(300, 400, dpi=600.0), fid="F-1", stem="front-k1")
    web = WebProcess(tmp_path).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 700})
            console = []
            page.on("console", lambda m: console.append((m.type, m.text)))
            open_viewer(page, f"{web.url}/fragments/F-1?face=front")
            assert page.evaluate("() => !!document.querySelector('style[data-openseadragon-mobile-css]')")
            browser.close()
    finally:
        web.stop()
    violations = [t for kind, t in console if "Content Security Policy" in t]
    assert not violations, violations


def test_the_csp_allows_exactly_the_style_the_vendored_openseadragon_injects():
    # a new OpenSeadragon (deploy/vendor-openseadragon.sh) with another inline style fails here,
    # not silently in the browser
    import base64
    import hashlib
    import re

    from services.web import OPENSEADRAGON_STYLE_HASH

    js = (REPO / "services/web/static/vendor/openseadragon/openseadragon.min.js").read_text()
    styles = re.findall(r'data-openseadragon-mobile-css","true"\);\w+\.textContent="([^"]*)"', js)
    assert len(styles) == 1
    digest = base64.b64encode(hashlib.sha256(styles[0].encode()).digest()).decode()
    assert OPENSEADRAGON_STYLE_HASH == f"sha256-{digest}"


@pytest.mark.slow
def test_the_top_level_is_the_first_picture_while_the_view_waits_for_its_tiles(tmp_path):
    """The one-tile top level (64 px) is drawn as soon as it arrives, whatever OpenSeadragon's queue
    holds: with every other tile held back, the face is already on the canvas; released, the tiles
    of the level the view needs replace it."""
    require_browser()
    from playwright.sync_api import sync_playwright

    from common.web.relight import TOP_PX, RelightCache

    store = _store_with(tmp_path, relief_face(1300, 2000, dpi=600.0))
    levels = RelightCache(store, "fragments/F-1/rgbn/front-k1.h5").params()["levels"]
    top = len(levels) - 1
    assert max(levels[top]) <= TOP_PX < max(levels[top - 1])
    web = WebProcess(tmp_path).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1000, "height": 800}, bypass_csp=True)
            held, release = [], []
            page.route("**/tiles/**", lambda route: route.continue_() if release or f"/tiles/{top}/0_0" in route.request.url
                       else held.append(route))
            page.goto(f"{web.url}/fragments/F-1")
            page.wait_for_function("() => window.tesseraViewer && tesseraViewer.stats.firstPictureMs !== null",
                                   timeout=60_000)
            s = page.evaluate("() => tesseraViewer.stats")
            assert s["tilesLoaded"] == 0 and held, "the first picture came before any tile OpenSeadragon asked for"
            # the face is drawn (the centre is on the fragment), not only the background
            centre = page.evaluate("""() => { const v = tesseraViewer, c = v.canvas; v.render();
                return Array.from(v.pixels(c.width / 2 - 1, c.height / 2 - 1, 2, 2)); }""")
            assert max(abs(c - 255) for i, c in enumerate(centre) if i % 4 != 3) > 10, centre
            release.append(True)
            for route in held:
                route.continue_()
            wait_complete(page)
            assert page.evaluate("() => tesseraViewer.stats.tilesLoaded") >= len(held)
            browser.close()
    finally:
        web.stop()
