"""The reconstruction page (services/web/reconstruction.py): JSON, live changes, exports; and in Chromium
against a real station: joins confirmed through the review API make the cluster grow.

The browser test needs Playwright and Debian's Chromium (skipped otherwise, as tests/web/test_browser.py);
``TESSERA_WEB_SCREENSHOTS=1`` writes its screenshots into docs/web/.
"""

from __future__ import annotations

import io
import json
import os
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from .conftest import TOKEN


def _seed(root, n=7, seed=2, dpi=40):
    """A small synthetic wall on storage and proposals of every pair at the true relative pose
    (true neighbours 0.9, others 0.1), as a matcher would leave them. Returns (wall, db path, true joins)."""
    from common.matching.proposals import Proposal, ProposalStore, ordered_pair
    from common.matching.reconstruction import relative_pose
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from common.synth.wall import generate_wall

    wall = generate_wall(n, seed=seed, dpi=dpi, surfaces=False, missing_fraction=0.0, spurious_fraction=0.0)
    store = Store(root)
    byid = {f.id: f for f in wall.fragments}
    for f in wall.fragments:
        save_rgbn(store, f"fragments/{f.id}/rgbn/front-groundtruth.h5", f.rgbn)
    props = []
    ids = sorted(byid)
    for i, a in enumerate(ids):
        for b in ids[i + 1:]:
            a_, b_ = ordered_pair(a, b)
            z = relative_pose(byid[a_].pose, byid[b_].pose)
            props.append(Proposal(a_, b_, 0.9 if wall.is_neighbour(a_, b_) else 0.1, "groundtruth",
                                  angle_deg=z[0], tx_mm=z[1], ty_mm=z[2]))
    db_path = root / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        db.upsert(props)
    true = sorted(ordered_pair(a, b) for a, b, _ in wall.adjacency)
    return wall, db_path, true


@pytest.fixture
def app_and_db(tmp_path):
    from common.store import Store
    from common.web.review import ReviewData
    from services import web

    wall, db_path, true = _seed(tmp_path)
    review = ReviewData(db_path, Store(tmp_path))
    app = web.create_app(token=TOKEN, store_root=tmp_path, review=review,
                         settings={"long_poll_s": 0.6})
    return app, db_path, wall, true


def test_clusters_follow_the_confirmed_joins(app_and_db):
    from common.matching.proposals import ProposalStore

    app, db_path, wall, true = app_and_db
    c = app.test_client()
    assert c.get("/reconstruction").status_code == 200
    empty = c.get("/api/reconstruction").get_json()
    assert empty["document"]["clusters"] == []
    sig = empty["signature"]
    # nothing changes: the long poll answers "unchanged" after long_poll_s
    t0 = time.monotonic()
    assert c.get(f"/api/reconstruction/changes?after={sig}").get_json()["changed"] is False
    assert time.monotonic() - t0 >= 0.5
    with ProposalStore(db_path) as db:
        db.record_verdict(*true[0], "confirmed", by="A. Conservator")
    assert c.get(f"/api/reconstruction/changes?after={sig}").get_json()["changed"] is True
    data = c.get("/api/reconstruction").get_json()
    (cluster,) = data["document"]["clusters"]
    assert sorted(f["fragment"] for f in cluster["fragments"]) == sorted(true[0])
    assert cluster["next_joins"] and all(n["member"] in true[0] for n in cluster["next_joins"])
    assert cluster["next_joins"][0]["probability"] == pytest.approx(0.9)
    # every fragment shown has a thumbnail at its size in mm
    for fid, info in data["fragments"].items():
        png = c.get(info["thumb"])
        assert png.status_code == 200 and png.mimetype == "image/png"
        img = cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_UNCHANGED)
        assert img.shape[2] == 4 and img[..., 3].max() == 255
        f = wall.fragment(fid)
        assert info["width_mm"] == pytest.approx(f.rgbn.shape[1] * f.rgbn.pixel_mm)
        # and its outline, which the page draws dashed around a next join's piece: it encloses the piece's area
        # and runs along the mask's boundary (within the 0.5 mm it is simplified to, and half a pixel)
        outline = np.array(info["outline_mm"], np.float32)
        area_mm2 = f.rgbn.mask.sum() * f.rgbn.pixel_mm ** 2
        assert cv2.contourArea(outline) == pytest.approx(area_mm2, rel=0.08)
        edge = f.rgbn.mask & ~cv2.erode(f.rgbn.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        ey, ex = np.nonzero(edge)
        d = np.hypot(outline[:, None, 0] - ex[None] * f.rgbn.pixel_mm, outline[:, None, 1] - ey[None] * f.rgbn.pixel_mm)
        assert d.min(axis=1).max() <= 0.5 + f.rgbn.pixel_mm
    with ProposalStore(db_path) as db:
        for pair in true[1:]:
            db.record_verdict(*pair, "confirmed")
    data = c.get("/api/reconstruction").get_json()
    (cluster,) = data["document"]["clusters"]
    assert len(cluster["fragments"]) == len(wall.fragments)
    assert cluster["n_conflicting_loops"] == 0


def test_a_wrong_confirmed_join_shows_as_a_conflicting_loop(app_and_db):
    from common.matching.proposals import ProposalStore

    from common.matching.reconstruction import closure_loops, confirmed_joins

    app, db_path, wall, true = app_and_db
    with ProposalStore(db_path) as db:
        for pair in true:
            db.record_verdict(*pair, "confirmed")
        # a true pair on a loop whose proposal pose was off by 25 degrees when it was confirmed (last)
        a, b = closure_loops(confirmed_joins(db)[0])[0].joins[0]
        db._db.execute("UPDATE proposals SET angle_deg = angle_deg + 25 WHERE fragment_a=? AND fragment_b=?", (a, b))
        db.record_verdict(a, b, "confirmed")
    data = app.test_client().get("/api/reconstruction").get_json()
    (cluster,) = data["document"]["clusters"]
    assert cluster["n_conflicting_loops"] >= 1
    assert all([a, b] in lp["joins"] for lp in cluster["loops"] if lp["conflicting"])
    assert cluster["blamed"] == [[a, b]]


def test_a_verdict_on_the_feed_shows_as_arriving_until_the_matcher_records_it(app_and_db):
    from common.matching.proposals import ProposalStore
    from common.messages import new_message
    from services.web.reconstruction import LIVE

    app, db_path, wall, true = app_and_db
    c = app.test_client()
    sig = c.get("/api/reconstruction").get_json()["signature"]
    a, b = true[0]
    event = new_message("match.verified", fragment=a, other=b, verdict="confirmed", by="A. Conservator")
    app.extensions[LIVE].on_verdict(event, 7)      # what the feed follower calls
    assert c.get(f"/api/reconstruction/changes?after={sig}").get_json()["changed"] is True
    data = c.get("/api/reconstruction").get_json()
    assert [(v["fragment_a"], v["fragment_b"], v["by"]) for v in data["arriving"]] == [(a, b, "A. Conservator")]
    assert data["document"]["clusters"] == []
    with ProposalStore(db_path) as db:             # the matcher records that message
        db.record_verdict(a, b, "confirmed", by="A. Conservator", message_uid=event["uid"], when=event["time"])
    data = c.get("/api/reconstruction").get_json()
    assert data["arriving"] == [] and len(data["document"]["clusters"]) == 1


def test_exports_composite_png_tiff_and_json(app_and_db):
    import tifffile

    from common.matching.proposals import ProposalStore

    app, db_path, wall, true = app_and_db
    with ProposalStore(db_path) as db:
        for pair in true:
            db.record_verdict(*pair, "confirmed")
    c = app.test_client()
    (cluster,) = c.get("/api/reconstruction").get_json()["document"]["clusters"]
    png = c.get(cluster["exports"]["png"])
    assert png.status_code == 200 and png.mimetype == "image/png"
    rgba = cv2.imdecode(np.frombuffer(png.data, np.uint8), cv2.IMREAD_UNCHANGED)
    tif = c.get(cluster["exports"]["tiff"])
    assert tif.status_code == 200
    t = tifffile.imread(io.BytesIO(tif.data))
    assert t.dtype == np.uint16 and t.shape == rgba.shape
    # coverage = the fragments' area (true joins do not overlap), at the fragments' 40 dpi
    px = 25.4 / 40
    area = sum(f.rgbn.mask.sum() for f in wall.fragments) * px ** 2
    assert (t[..., 3] / 65535.0).sum() * px ** 2 == pytest.approx(area, rel=0.03)
    doc = json.loads(c.get("/api/reconstruction/poses.json").data)
    assert doc["schema"] == "tessera.reconstruction"
    assert c.get("/api/reconstruction/NOPE/composite.png").status_code == 404
    assert c.get("/api/reconstruction/thumb/..%2Fetc.png").status_code in (400, 404)


def test_the_json_export_is_strict_an_undefined_figure_as_null(app_and_db, monkeypatch):
    """poses.json was written by json.dumps: a NaN or infinite figure came out as bare ``NaN`` / ``Infinity``,
    which a browser's JSON.parse refuses; it is null, as in ``tessera reconstruct``'s reconstruction.json."""
    from common.matching import reconstruction as rc
    from common.matching.proposals import ProposalStore

    app, db_path, wall, true = app_and_db
    with ProposalStore(db_path) as db:
        for pair in true:
            db.record_verdict(*pair, "confirmed")
    real = rc.reconstruction_document

    def undefined(*args, **kwargs):   # figures the document may hold undefined (no path gives one today)
        doc = real(*args, **kwargs)
        if doc["clusters"]:
            c = doc["clusters"][0]
            c["solve"]["cost"], c["joins"][0]["residual_mm"] = float("inf"), float("nan")
        return doc
    monkeypatch.setattr(rc, "reconstruction_document", undefined)

    def refuse(name):
        raise AssertionError(f"{name} is not JSON")
    (c,) = json.loads(app.test_client().get("/api/reconstruction/poses.json").data, parse_constant=refuse)["clusters"]
    assert c["solve"]["cost"] is None and c["joins"][0]["residual_mm"] is None
    assert {d["fragment"] for d in c["fragments"]} == {f for pair in true for f in pair}   # the rest as it was


def test_next_joins_are_tried_in_the_clusters_corners_in_the_background(tmp_path):
    """The page answers at once with the proposals' poses and docks the newcomers against their cluster in the
    background; when that lands the signature changes and the page shows the fits ``tessera reconstruct`` gives
    (the library's next_joins with the feature tables' outlines) beside the proposals' poses. Docked once:
    reloading docks nothing anew."""
    from common.matching.proposals import ProposalStore
    from common.matching.reconstruction import front_pieces, reconstruct
    from common.store import Store
    from common.web.review import ReviewData
    from services import web
    from services.web.reconstruction import LIVE
    from tests.matching.test_reconstruction import station_with_a_cluster

    wall, db_path, pair = station_with_a_cluster(tmp_path)
    app = web.create_app(token=TOKEN, store_root=tmp_path, review=ReviewData(db_path, Store(tmp_path)),
                         settings={"long_poll_s": 0.5})
    c = app.test_client()
    first = c.get("/api/reconstruction").get_json()
    (cluster,) = first["document"]["clusters"]
    assert first["docking"] is True and all(n["fit"] is None for n in cluster["next_joins"])
    sig = first["signature"]
    deadline = time.monotonic() + 60
    while not c.get(f"/api/reconstruction/changes?after={sig}").get_json()["changed"]:
        assert time.monotonic() < deadline, "the docking never landed"
    data = c.get("/api/reconstruction").get_json()
    (cluster,) = data["document"]["clusters"]
    with ProposalStore(db_path) as db:
        want = reconstruct(db, pieces=lambda fs: front_pieces(Store(tmp_path), db.fragments(face="front"), fs)[0])
    (expected,) = want["next"].values()
    assert data["docking"] is False
    assert [(n["newcomer"], n["fit"] is None) for n in cluster["next_joins"]] == \
        [(n["newcomer"], n["fit"] is None) for n in expected]
    corner = [n for n in cluster["next_joins"] if n["fit"] is not None]
    assert corner and all(sorted(n["faces"]) == sorted(pair) for n in corner)
    for got, n in zip(cluster["next_joins"], expected):
        for k in ("pose", "fit"):
            if n[k] is not None:
                assert [got[k]["angle_deg"], got[k]["tx_mm"], got[k]["ty_mm"]] == pytest.approx(list(n[k]))
    # the fragment without a feature table gets no fit; nothing is docked again
    assert all(n["fit"] is None for n in cluster["next_joins"] if n["newcomer"] == wall.fragments[0].id)
    live = app.extensions[LIVE]
    docked, rounds = dict(live.docked), live.dock_round
    with ProposalStore(db_path) as db:                      # a verdict elsewhere: the page is recomputed
        db.record_verdict(*sorted(set(f.id for f in wall.fragments) - set(pair))[:2], "rejected")
    again = c.get("/api/reconstruction").get_json()
    assert again["signature"] != data["signature"] and again["docking"] is False
    assert live.docked == docked and live.dock_round == rounds


def test_the_review_page_offers_a_corner_newcomer_its_fit_in_the_cluster(tmp_path):
    """A pending proposal whose newcomer fits a corner of a confirmed cluster is offered that pose on the review
    page (``/api/review/alternatives``' ``cluster``: the adjustment of the proposal's pose that reaches it),
    the pose tessera reconstruct gives it, as B in A's frame; once the docking has landed. A proposal whose newcomer
    fits no corner has none."""
    from common.matching.proposals import ProposalStore
    from common.matching.reconstruction import front_pieces, reconstruct, relative_pose
    from common.store import Store
    from common.web.review import ReviewData
    from services import web
    from tests.matching.test_reconstruction import station_with_a_cluster

    _, db_path, pair = station_with_a_cluster(tmp_path)
    review = ReviewData(db_path, Store(tmp_path))
    app = web.create_app(token=TOKEN, store_root=tmp_path, review=review, settings={"long_poll_s": 0.5})
    c = app.test_client()
    with ProposalStore(db_path) as db:
        want = reconstruct(db, pieces=lambda fs: front_pieces(Store(tmp_path), db.fragments(face="front"), fs)[0])
    (cluster,) = want["clusters"]
    (nexts,) = want["next"].values()
    corner = next(n for n in nexts if n["fit"] is not None)
    plain = next(n for n in nexts if n["fit"] is None and n["pose"] is not None)

    deadline = time.monotonic() + 60
    while (got := c.get(f"/api/review/alternatives/{corner['proposal']}").get_json())["docking"]:
        assert time.monotonic() < deadline, "the docking never landed"
        time.sleep(0.2)
    fit = got["cluster"]
    assert fit is not None and sorted(fit["faces"]) == sorted(pair)
    prop = review.proposal(corner["proposal"])
    at = {corner["member"]: cluster.poses[corner["member"]], corner["newcomer"]: corner["fit"]}
    expected = relative_pose(at[prop["fragment_a"]], at[prop["fragment_b"]])
    shown = review.adjusted_pose(prop["id"], fit["turn_deg"], (fit["shift_x_mm"], fit["shift_y_mm"]))
    assert [shown["angle_deg"], shown["tx_mm"], shown["ty_mm"]] == pytest.approx(list(expected), abs=1e-6)
    other = c.get(f"/api/review/alternatives/{plain['proposal']}").get_json()
    assert other["cluster"] is None and other["docking"] is False


def test_without_a_proposal_store_the_api_says_so(tmp_path):
    from services import web

    app = web.create_app(token=TOKEN, store_root=tmp_path)
    c = app.test_client()
    for url in ("/api/reconstruction", "/api/review/queue", "/api/catalogue"):
        r = c.get(url)   # said in JSON, so the page shows the reason and not a generic failure
        assert r.status_code == 503 and "not available on this station" in r.get_json()["error"], url


# -- in Chromium, against a real station ------------------------------------------------------
@pytest.mark.slow
def test_confirming_joins_grows_the_cluster_live_in_the_browser(tmp_path):
    from .test_browser import BENCH_CHROMIUM_ARGS, DOCS, LiveStation
    from .viewer_support import CHROMIUM, require_browser

    require_browser()
    from playwright.sync_api import sync_playwright

    live = LiveStation(tmp_path)
    wall, db_path, true = _seed(Path(live.config["storage"]["root"]), n=8, seed=5, dpi=50)
    # one wrong pair, confirmed last: two pieces that are not neighbours, proposed at a wrong pose
    from common.matching.proposals import ProposalStore
    ids = sorted(f.id for f in wall.fragments)
    wrong = next((a, b) for a in ids for b in ids if a < b and not wall.is_neighbour(a, b))
    with ProposalStore(db_path) as db:
        db._db.execute("UPDATE proposals SET angle_deg = angle_deg + 30, tx_mm = tx_mm + 20 "
                       "WHERE fragment_a=? AND fragment_b=?", wrong)
    shots = DOCS if os.environ.get("TESSERA_WEB_SCREENSHOTS") == "1" else tmp_path / "screenshots"
    shots.mkdir(parents=True, exist_ok=True)
    live.start()
    try:
        def confirm(pair):
            with ProposalStore(db_path) as db:
                pid = db.get(*pair).id
            req = urllib.request.Request(f"{live.url}/api/review/verdict", method="POST",
                                         data=json.dumps({"proposal": pid, "verdict": "confirmed"}).encode(),
                                         headers={"Content-Type": "application/json",
                                                  "Authorization": f"Bearer {TOKEN}"})
            assert urllib.request.urlopen(req, timeout=10).status == 200

        def cluster(attr):
            return (f"() => {{ const c = document.querySelector('.cluster'); "
                    f"return c ? +c.dataset.{attr} : 0; }}")

        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BENCH_CHROMIUM_ARGS)
            page = browser.new_context(viewport={"width": 1280, "height": 900}).new_page()
            page.goto(f"{live.url}/reconstruction")
            page.wait_for_selector("#recon-empty:not([hidden])", timeout=30_000)
            confirm(true[0])
            if "matcher" not in live.stages:   # nobody records verdicts: the page shows them arriving
                page.wait_for_selector("#arriving li", timeout=60_000)
                browser.close()
                return
            # the matcher records the verdict; the page follows without a reload
            page.wait_for_function(f"() => ({cluster('size')})() === 2", timeout=120_000)
            half = len(true) // 2
            for pair in true[1:half]:
                confirm(pair)
            page.wait_for_function(f"() => ({cluster('joins')})() === {half}", timeout=120_000)
            page.wait_for_selector(".cluster-svg .piece.ghost", timeout=10_000)   # next joins where they would go
            page.wait_for_timeout(500)
            page.screenshot(path=str(shots / "reconstruction-growing.png"), full_page=True)
            for pair in true[half:]:
                confirm(pair)
            page.wait_for_function(f"() => ({cluster('joins')})() === {len(true)}", timeout=180_000)
            assert page.locator(".cluster-svg .piece.placed").count() == len(wall.fragments)
            assert page.inner_text(".cluster .conflicts") == "loops consistent"
            page.wait_for_selector("#arriving", state="hidden", timeout=30_000)
            page.wait_for_timeout(500)
            page.screenshot(path=str(shots / "reconstruction.png"), full_page=True)
            # the wrong join closes a loop that does not close: shown in red, not hidden
            confirm(wrong)
            page.wait_for_function(f"() => ({cluster('conflicts')})() >= 1", timeout=120_000)
            assert page.locator(".cluster-svg .loop.conflicting").count() >= 1
            assert "conflicting loop" in page.inner_text(".cluster .conflicts")
            # the join confirmed last is the one set aside
            page.wait_for_selector(f".cluster .loops li.blamed:has-text('{wrong[0]} ↔ {wrong[1]}')", timeout=10_000)
            page.wait_for_timeout(500)
            page.screenshot(path=str(shots / "reconstruction-conflict.png"), full_page=True)
            # the exports answer from the page's links
            href = page.get_attribute(".cluster a.export-png", "href")
            with urllib.request.urlopen(live.url + href, timeout=60) as r:
                assert r.headers["Content-Type"] == "image/png" and len(r.read()) > 1000
            browser.close()
    except Exception:
        print(live.logs())
        raise
    finally:
        live.stop()


@pytest.mark.slow
def test_the_review_page_offers_the_corner_fit_in_the_browser(tmp_path):
    """In Chromium, against ``tessera web``: a proposal whose newcomer fits a corner of a confirmed cluster opens
    at its own pose, and P steps to the fit, saying so (the joined picture at it); P again goes on."""
    from common.matching.proposals import ProposalStore
    from common.matching.reconstruction import front_pieces, reconstruct
    from common.store import Store
    from tests.matching.test_reconstruction import station_with_a_cluster

    from .test_browser import BENCH_CHROMIUM_ARGS
    from .viewer_support import CHROMIUM, WebProcess, require_browser

    require_browser()
    from playwright.sync_api import sync_playwright

    _, db_path, pair = station_with_a_cluster(tmp_path / "storage")
    with ProposalStore(db_path) as db:
        want = reconstruct(db, pieces=lambda fs: front_pieces(Store(tmp_path / "storage"),
                                                               db.fragments(face="front"), fs)[0])
    (nexts,) = want["next"].values()
    corner = next(n for n in nexts if n["fit"] is not None)
    web = WebProcess(tmp_path).start()
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=BENCH_CHROMIUM_ARGS)
            page = browser.new_context(viewport={"width": 1280, "height": 900}).new_page()
            deadline = time.monotonic() + 60                 # the web app docks in the background first
            while True:
                with urllib.request.urlopen(f"{web.url}/api/review/alternatives/{corner['proposal']}") as r:
                    if json.load(r)["cluster"] is not None:
                        break
                assert time.monotonic() < deadline, "the docking never landed"
                time.sleep(0.5)
            page.goto(f"{web.url}/review?fragment={corner['newcomer']}")
            page.click(f"#queue li[data-proposal='{corner['proposal']}']")
            page.wait_for_function("() => document.getElementById('joined-colour').src.includes('/joined-colour.png')")
            assert "turn_deg=" not in page.get_attribute("#joined-colour", "src")    # its own pose first
            page.keyboard.press("p")
            page.wait_for_selector("#pose-adjust:has-text('fitted into the corner of')", timeout=10_000)
            assert all(f in page.inner_text("#pose-adjust") for f in pair)
            assert "candidate pose 2 of" in page.inner_text("#pose-adjust")
            assert "turn_deg=" in page.get_attribute("#joined-colour", "src")
            page.keyboard.press("p")                        # on to the docking's next candidate
            page.wait_for_function("() => !document.getElementById('pose-adjust').textContent.includes('corner')",
                                   timeout=10_000)
            browser.close()
    finally:
        web.stop()
