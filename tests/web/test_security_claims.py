"""docs/web.md "Access" and docs/security.md against the web app: every page, the archive's too,
loads only what the station serves (no CDN, no font or script from elsewhere), under a
Content-Security-Policy of 'self'; every static file of ours names no outside address; the vendored
OpenSeadragon is the file its vendoring script recorded."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np
import pytest

from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from services import web

from .conftest import TOKEN

STATIC = Path(web.__file__).resolve().parent / "static"
TEMPLATES = Path(web.__file__).resolve().parent / "templates"
VENDOR = STATIC / "vendor"
# identifiers that look like addresses but are never fetched (XML namespaces)
_NOT_FETCHED = {"http://www.w3.org/2000/svg"}


@pytest.fixture
def archive_app(tmp_path):
    from common.web.catalogue import Catalogue
    store = Store(tmp_path)
    h, w = 40, 50
    img = RGBNImage(albedo=np.full((h, w, 3), 0.5), mask=np.ones((h, w), bool), dpi=300.0,
                    normals=np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))]))
    save_rgbn(store, "fragments/F1/rgbn/front-0123456789abcdef.h5", img)
    return web.create_app(token=TOKEN, store_root=tmp_path, catalogue=Catalogue(tmp_path / "web" / "cat.sqlite", store))


def test_every_page_the_archive_included_loads_only_the_stations_assets(archive_app):
    """test_web.py checked the bench, review, status and login pages; the archive's pages
    (catalogue, fragment page, reconstruction) are pages of the same station."""
    c = archive_app.test_client()
    for page in ("/bench", "/review", "/status", "/login", "/fragments", "/fragments/F1", "/reconstruction"):
        r = c.get(page)
        assert r.status_code == 200, page
        html = r.get_data(as_text=True)
        refs = re.findall(r'(?:src|href)="([^"]*)"', html)
        assert refs and all(ref.startswith("/") and not ref.startswith("//") for ref in refs), (page, refs)
        for ref in refs:
            if ref.startswith("/static/"):
                assert c.get(ref).status_code == 200, (page, ref)
        csp = r.headers["Content-Security-Policy"]
        assert "default-src 'self'" in csp and "script-src 'self'" in csp and "frame-ancestors 'none'" in csp, page
        assert r.headers["X-Frame-Options"] == "DENY"


def test_no_static_file_or_template_names_an_outside_address():
    """Our files, that is: the vendored libraries (static/vendor/) carry addresses that are
    identifiers (IIIF contexts, the Deep Zoom namespace) or defaults of tile sources the station
    never opens; what the fragment page really requests, OpenSeadragon's included, is checked in
    Chromium (test_fragment_page.py: every request goes to the station)."""
    files = [p for p in [*STATIC.rglob("*"), *TEMPLATES.rglob("*")] if p.is_file() and not p.is_relative_to(VENDOR)]
    assert any(p.suffix == ".js" for p in files) and any(p.suffix == ".frag" for p in files)
    found = []
    for p in files:
        text = p.read_text(errors="replace")
        found += [f"{p.name}: {u}" for u in re.findall(r"https?://[^\s\"'<>)`]+", text) if u not in _NOT_FETCHED]
    assert not found, found


def test_api_answers_are_not_cached_and_carry_the_same_policy(archive_app):
    r = archive_app.test_client().get("/api/catalogue")
    assert r.status_code == 200
    assert r.headers["Cache-Control"] == "no-store" and "default-src 'self'" in r.headers["Content-Security-Policy"]


def test_the_served_openseadragon_is_the_vendored_release(archive_app):
    """deploy/vendor-openseadragon.sh recorded the npm release's sha256 beside the file; the station
    serves exactly that file, with its licence, and the fragment page loads it from the station."""
    folder = VENDOR / "openseadragon"
    recorded, name = (folder / "openseadragon.min.js.sha256").read_text().split()
    assert name == "openseadragon.min.js" and (folder / "VERSION").read_text().strip() == "6.1.1"
    c = archive_app.test_client()
    r = c.get("/static/vendor/openseadragon/openseadragon.min.js")
    assert r.status_code == 200 and hashlib.sha256(r.data).hexdigest() == recorded
    assert b"openseadragon 6.1.1" in r.data[:200]
    assert "Redistribution and use in source and binary forms" in (folder / "LICENSE.txt").read_text()   # BSD-3
    # (its URL carries the file's version: the first 12 hex digits of that same sha256)
    assert f'<script src="/static/vendor/openseadragon/openseadragon.min.js?v={recorded[:12]}">' in \
        c.get("/fragments/F1").get_data(as_text=True)
