"""Tests of IIIF: common/web/iiif.py (parsing, level choice) and the /iiif endpoints against the source pixels."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from common.rgbn.image import RGBNImage, save_rgbn
from common.rgbn.io import linear_to_srgb
from common.store import Store
from common.web import iiif

from .conftest import TOKEN


# -- parsing (IIIF Image API 3.0 §4) -------------------------------------------------------------

@pytest.mark.parametrize("region, want", [
    ("full", (0, 0, 400, 300)), ("square", (50, 0, 300, 300)), ("10,20,30,40", (10, 20, 30, 40)),
    ("350,250,100,100", (350, 250, 50, 50)), ("pct:25,50,50,50", (100, 150, 200, 150))])
def test_regions(region, want):
    assert iiif.parse_region(region, 400, 300) == want


@pytest.mark.parametrize("region", ["400,0,10,10", "0,0,0,10", "1.5,0,10,10", "left", "pct:1,2,3"])
def test_bad_regions_are_400(region):
    with pytest.raises(iiif.IIIFError) as e:
        iiif.parse_region(region, 400, 300)
    assert e.value.status == 400


@pytest.mark.parametrize("size, want", [
    ("max", (400, 300)), ("200,", (200, 150)), (",150", (200, 150)), ("200,100", (200, 100)),
    ("!200,200", (200, 150)), ("pct:50", (200, 150)), ("^800,", (800, 600)),
    ("!800,800", (400, 300)), ("^!800,800", (800, 600)), ("^!800,450", (600, 450))])
def test_sizes(size, want):
    assert iiif.parse_size(size, 400, 300) == want


def test_caret_max_is_the_region_scaled_to_max_area():
    # Image API 3.0 §4.2: "^max: the extracted region is scaled to the maximum size permitted by
    # maxWidth, maxHeight, or maxArea" (this server has maxArea only)
    w, h = iiif.parse_size("^max", 400, 300, max_area=1_000_000)
    assert w * h <= 1_000_000 and (w + 2) * (h + 2) > 1_000_000 and abs(w / h - 4 / 3) < 0.01
    assert iiif.parse_size("^max", 400, 300) == (4729, 3547)


def test_sizes_beyond_the_region_need_the_caret_and_max_is_limited_by_max_area():
    with pytest.raises(iiif.IIIFError, match="upscale"):
        iiif.parse_size("800,", 400, 300)
    w, h = iiif.parse_size("max", 8000, 6000, max_area=1_000_000)
    assert w * h <= 1_000_000 and abs(w / h - 8 / 6) < 0.01
    with pytest.raises(iiif.IIIFError, match="more than"):
        iiif.parse_size("^4000,", 400, 300, max_area=1_000_000)


def test_requests_accept_rotations_by_90s_the_three_qualities_and_jpg_or_png_only():
    r = iiif.parse_request("full", "max", "0", "color.png", 40, 30)
    assert (r.width, r.height, r.fmt, r.rotation, r.mirror) == (40, 30, "png", 0, False)
    r = iiif.parse_request("full", "max", "!270", "gray.jpg", 40, 30)
    assert (r.rotation, r.mirror, r.quality) == (270, True, "gray")
    r = iiif.parse_request("full", "max", "360", "bitonal.png", 40, 30)
    assert (r.rotation, r.quality) == (0, "bitonal")
    for args, phrase in ((("45", "default.jpg"), "rotation"), (("-90", "default.jpg"), "rotation"),
                         (("0", "grey.jpg"), "quality"), (("0", "default.gif"), "format")):
        with pytest.raises(iiif.IIIFError, match=phrase):
            iiif.parse_request("full", "max", *args, 40, 30)


@pytest.mark.parametrize("args, want", [
    (("full", "max", "0", "default.jpg"), "full/max/0/default.jpg"),
    (("0,0,400,300", "pct:100", "0.0", "default.jpg"), "full/max/0/default.jpg"),
    (("square", "!100,100", "!90", "color.png"), "50,0,300,300/100,100/!90/color.png"),
    (("pct:50,50,100,100", "100,", "180", "gray.jpg"), "200,150,200,150/100,75/180/gray.jpg"),
    (("10,10,20,20", "^40,", "0", "bitonal.png"), "10,10,20,20/^40,40/0/bitonal.png"),
    (("full", "^max", "0", "default.jpg"), "full/^max/0/default.jpg")])
def test_canonical_paths(args, want):
    # Image API 3.0 §4.8: full or x,y,w,h; max, w,h or ^w,h; ! and an integer; the quality asked
    assert iiif.canonical_path(iiif.parse_request(*args, 400, 300), 400, 300) == want


def test_the_level_is_the_coarsest_with_enough_resolution():
    req = lambda w, ow: iiif.ImageRequest(0, 0, w, w, ow, ow, "png")  # noqa: E731
    assert iiif.pyramid_level_for(req(1024, 1024), 5) == 0
    assert iiif.pyramid_level_for(req(1024, 512), 5) == 1
    assert iiif.pyramid_level_for(req(1024, 300), 5) == 1     # 3.4x smaller: level 1 (2x), then resampled
    assert iiif.pyramid_level_for(req(1024, 10), 5) == 4      # never past the top level
    assert iiif.pyramid_level_for(req(100, 400), 5) == 0      # upscaling reads full resolution


# -- the endpoints ---------------------------------------------------------------------------

@pytest.fixture
def station(tmp_path):
    from services import web

    store = Store(tmp_path)
    h, w = 300, 520
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = np.stack([0.2 + 0.6 * xx / w, 0.2 + 0.6 * yy / h, 0.5 + 0.3 * np.sin(xx / 23.0)], axis=2)
    normals = np.dstack([0.3 * np.sin(yy / 19.0), np.zeros_like(xx), np.ones_like(xx)])
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    meta = json.dumps({"inventory": "INV-77", "find_spot": "Room 2"})
    save_rgbn(store, "fragments/F7/rgbn/front-00000000000000f7.h5",
              RGBNImage(albedo, np.ones((h, w), bool), 254.0, normals=normals, attrs={"metadata": meta}))
    save_rgbn(store, "fragments/F7/rgbn/back-00000000000000b7.h5", RGBNImage(albedo[:, ::-1], np.ones((h, w), bool), 254.0))
    srgb = np.round(linear_to_srgb(albedo) * 255).astype(np.uint8)
    return web.create_app(token=TOKEN, store_root=tmp_path).test_client(), srgb


def _png(data):
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED), cv2.COLOR_BGRA2RGBA)


def test_info_json_describes_the_image_and_its_tiles(station):
    c, srgb = station
    r = c.get("/iiif/image/F7~front~albedo/info.json")
    assert r.status_code == 200 and "application/ld+json" in r.headers["Content-Type"]
    assert r.headers["Access-Control-Allow-Origin"] == "*"
    info = json.loads(r.data)
    assert info["@context"] == "http://iiif.io/api/image/3/context.json" and info["type"] == "ImageService3"
    assert info["id"] == "http://localhost/iiif/image/F7~front~albedo" and info["profile"] == "level2"
    # §4.4: every quality beyond default is listed, color included; §6: the level's profile document
    assert info["extraQualities"] == ["color", "gray", "bitonal"]
    assert r.headers["Link"] == '<http://iiif.io/api/image/3/level2.json>;rel="profile"'
    assert (info["width"], info["height"]) == (520, 300)
    assert info["tiles"] == [{"width": 256, "height": 256, "scaleFactors": [1, 2, 4]}]
    assert info["sizes"][0] == {"width": 130, "height": 75} and info["sizes"][-1] == {"width": 520, "height": 300}
    assert c.get("/iiif/image/F7~front~albedo").status_code == 303
    assert c.get("/iiif/image/F7~side~albedo/info.json").status_code == 404
    assert c.get("/iiif/image/F7~back~normals/info.json").status_code == 404   # colour-only face
    assert c.get("/iiif/image/nonsense/info.json").status_code == 404


def test_cors_preflight_answers_any_origin(station):
    # Image API 3.0 §7.1: CORS, "including the Access-Control-Allow-Origin header and the preflight
    # request pattern" — a viewer on another site sending a non-simple header must get through
    c, _ = station
    for url in ("/iiif/image/F7~front~albedo/info.json", "/iiif/image/F7~front~albedo/0,0,256,256/256,/0/default.png",
                "/iiif/presentation/F7/manifest"):
        r = c.options(url, headers={"Origin": "https://museum.example", "Access-Control-Request-Method": "GET",
                                    "Access-Control-Request-Headers": "accept, x-requested-with"})
        assert r.status_code == 200, url
        assert r.headers["Access-Control-Allow-Origin"] == "*"
        assert "GET" in r.headers["Access-Control-Allow-Methods"]
        assert r.headers["Access-Control-Allow-Headers"] == "accept, x-requested-with"
        g = c.get(url, headers={"Origin": "https://museum.example"})
        assert g.status_code == 200 and g.headers["Access-Control-Allow-Origin"] == "*"
    assert c.head("/iiif/image/F7~front~albedo/full/max/0/default.jpg").status_code == 200


def test_regions_at_full_size_are_the_source_pixels(station):
    c, srgb = station
    r = c.get("/iiif/image/F7~front~albedo/100,50,300,200/max/0/default.png")
    assert r.status_code == 200 and r.headers["Content-Type"] == "image/png"
    got = _png(r.data)
    assert got.shape == (200, 300, 4)
    assert np.abs(got[..., :3].astype(int) - srgb[50:250, 100:400]).max() <= 1 and (got[..., 3] == 255).all()
    full = _png(c.get("/iiif/image/F7~front~albedo/full/max/0/color.png").data)
    assert np.abs(full[..., :3].astype(int) - srgb).max() <= 1


def test_rotation_mirroring_and_gray_are_applied_after_the_size(station):
    c, srgb = station
    region = srgb[50:250, 100:400]
    for rotation, want in (("90", np.rot90(region, -1)), ("180", np.rot90(region, 2)), ("270", np.rot90(region, 1)),
                           ("!0", region[:, ::-1]), ("!90", np.rot90(region[:, ::-1], -1))):
        got = _png(c.get(f"/iiif/image/F7~front~albedo/100,50,300,200/max/{rotation}/default.png").data)
        assert got.shape[:2] == want.shape[:2], rotation
        assert np.abs(got[..., :3].astype(int) - want).max() <= 1, rotation
    gray = _png(c.get("/iiif/image/F7~front~albedo/100,50,300,200/max/0/gray.png").data)
    luma = region.astype(float) @ [0.299, 0.587, 0.114]
    assert np.abs(gray[..., 0].astype(float) - luma).max() <= 1.5
    assert np.array_equal(gray[..., 0], gray[..., 1]) and (gray[..., 3] == 255).all()
    bitonal = _png(c.get("/iiif/image/F7~front~albedo/100,50,300,200/max/0/bitonal.png").data)
    assert set(np.unique(bitonal[..., :3])) <= {0, 255} and np.array_equal(bitonal[..., 0], bitonal[..., 2])
    assert ((bitonal[..., 0] == 255) == (gray[..., 0] >= 128)).all() and (bitonal[..., 3] == 255).all()


def test_sizes_are_area_averages_of_the_source(station):
    c, srgb = station
    # half size of an aligned region: the pyramid's level 1, an exact 2 x 2 average (in linear light)
    got = _png(c.get("/iiif/image/F7~front~albedo/0,0,512,256/256,/0/default.png").data)
    assert got.shape == (128, 256, 4)
    want = cv2.resize(srgb[:256, :512], (256, 128), interpolation=cv2.INTER_AREA)
    # averaging in linear light before the sRGB encoding differs from averaging sRGB codes by a little
    assert np.abs(got[..., :3].astype(int) - want).mean() < 1.0 and np.abs(got[..., :3].astype(int) - want).max() <= 3
    # any other size: resampled from the level above it
    got = _png(c.get("/iiif/image/F7~front~albedo/full/!100,100/0/default.png").data)
    assert got.shape == (58, 100, 4)
    want = cv2.resize(srgb, (100, 58), interpolation=cv2.INTER_AREA)
    assert np.abs(got[..., :3].astype(int) - want).mean() < 2.0
    jpg = c.get("/iiif/image/F7~front~albedo/full/pct:25/0/default.jpg")
    assert jpg.headers["Content-Type"] == "image/jpeg"
    img = cv2.cvtColor(cv2.imdecode(np.frombuffer(jpg.data, np.uint8), 1), cv2.COLOR_BGR2RGB)
    assert img.shape == (75, 130, 3)
    assert np.abs(img.astype(int) - cv2.resize(srgb, (130, 75), interpolation=cv2.INTER_AREA)).mean() < 3.0
    assert c.get("/iiif/image/F7~front~albedo/full/max/45/default.jpg").status_code == 400
    assert c.get("/iiif/image/F7~front~albedo/full/1000,/0/default.jpg").status_code == 400


def test_the_manifest_has_a_canvas_per_face_metadata_and_the_normal_map(station):
    c, srgb = station
    r = c.get("/iiif/presentation/F7/manifest")
    assert r.status_code == 200 and r.headers["Access-Control-Allow-Origin"] == "*"
    m = json.loads(r.data)
    assert m["@context"] == "http://iiif.io/api/presentation/3/context.json" and m["type"] == "Manifest"
    assert [cv["label"]["en"][0] for cv in m["items"]] == ["F7 front", "F7 back"]   # front first: what viewers open
    front = m["items"][0]
    assert (front["width"], front["height"]) == (520, 300)
    body = front["items"][0]["items"][0]["body"]
    assert body["service"][0]["id"] == "http://localhost/iiif/image/F7~front~albedo"
    assert front["rendering"][0]["id"].endswith("F7~front~normals/full/max/0/default.png")
    assert "rendering" not in m["items"][1]                      # the back face has no normals
    assert front["service"][0]["physicalScale"] == pytest.approx(0.1)
    labels = {e["label"]["en"][0]: e["value"]["none"][0] for e in m["metadata"]}
    assert labels == {"Inventory": "INV-77", "Find-spot": "Room 2"}
    # every image the manifest names can be fetched
    for url in (body["id"], front["rendering"][0]["id"]):
        assert c.get(url.replace("http://localhost", "")).status_code == 200
    assert c.get("/iiif/presentation/F8/manifest").status_code == 404



def test_renders_are_offered_as_a_choice_on_the_canvas(station, tmp_path):
    c, srgb = station
    store = Store(tmp_path)
    drawn = np.full((300, 520, 3), 200, np.uint8)

    def fill(f):
        f.create_dataset("image", data=drawn)
        f.create_dataset("alpha", data=np.full((300, 520), 255, np.uint8))
        f.attrs.update(recipe="toon", bits=8, dpi=254.0)

    store.write("fragments/F7/renders/front-00000000000000e7.h5", "tessera.render", 1, fill,
                provenance={"inputs": [{"path": "fragments/F7/rgbn/front-00000000000000f7.h5"}]})
    m = json.loads(c.get("/iiif/presentation/F7/manifest").data)
    body = m["items"][0]["items"][0]["items"][0]["body"]
    assert body["type"] == "Choice"
    assert [b["label"]["en"][0] for b in body["items"]] == ["albedo", "render-toon"]
    got = cv2.imdecode(np.frombuffer(c.get(body["items"][1]["id"].replace("http://localhost", "")).data, np.uint8), 1)
    assert got.shape == (300, 520, 3) and np.abs(got.astype(int) - 200).max() <= 2   # jpg of the drawn image


# -- the manifest against the IIIF Presentation 3 models (PyPI iiif-prezi3) -------------------------

def _differences(a, b, path=""):
    """Where JSON ``b`` differs from ``a``: paths of missing keys and changed values."""
    if type(a) is not type(b):
        return [f"{path}: {a!r} -> {b!r}"]
    if isinstance(a, dict):
        return [f"{path}/{k}" for k in a.keys() ^ b.keys()] + \
            [d for k in a.keys() & b.keys() for d in _differences(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, list):
        return [f"{path}: {len(a)} -> {len(b)} items"] if len(a) != len(b) else \
            [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{path}[{i}]")]
    return [] if a == b else [f"{path}: {a!r} -> {b!r}"]


@pytest.mark.parametrize("with_render", [False, True])
def test_manifests_are_valid_presentation_3_models(station, tmp_path, with_render):
    """The manifest loads into iiif-prezi3's Manifest (pydantic, strict: types, absolute URL ids,
    language maps, services, annotation pages, Choice bodies) and comes back out the same, but for
    what its ``rendering`` model (an external link: id, type, label, format) does not keep."""
    from iiif_prezi3 import Manifest

    c, _ = station
    if with_render:
        drawn = np.full((300, 520, 3), 200, np.uint8)

        def fill(f):
            f.create_dataset("image", data=drawn)
            f.create_dataset("alpha", data=np.full((300, 520), 255, np.uint8))
            f.attrs.update(recipe="toon", bits=8, dpi=254.0)
        Store(tmp_path).write("fragments/F7/renders/front-00000000000000e7.h5", "tessera.render", 1, fill,
                              provenance={"inputs": [{"path": "fragments/F7/rgbn/front-00000000000000f7.h5"}]})
    m = json.loads(c.get("/iiif/presentation/F7/manifest").data)
    model = Manifest(**m)                                  # raises pydantic.ValidationError on any error
    assert str(model.id) == m["id"] and len(model.items) == 2
    back = json.loads(model.jsonld())
    assert back["@context"] == "http://iiif.io/api/presentation/3/context.json"
    dropped = {f"/items[0]/rendering[0]/{k}" for k in ("service", "width", "height")}
    assert set(_differences(m, back)) == dropped
    # thumbnails: the albedo at a size the image service lists as fitting, and it is served at that size
    thumb = m["thumbnail"][0]
    assert (thumb["width"], thumb["height"]) == (256, 148) and thumb["id"].endswith("/full/256,148/0/default.jpg")
    img = cv2.imdecode(np.frombuffer(c.get(thumb["id"].replace("http://localhost", "")).data, np.uint8), 1)
    assert img.shape == (148, 256, 3)
