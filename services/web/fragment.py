"""The fragment page (``/fragments/<id>``): front and back relit live in WebGL, deep zoom, measuring.

The page (``templates/fragment.html``, ``static/fragment.js``) runs the relighting viewer
(``static/viewer/``) on the tiles of :class:`common.web.relight.RelightCache`: fields computed once
per face from its newest RGBN artifact and kept on storage. Its JSON says what the fragment has:
faces (size, dpi), its proposals and confirmed joins from the proposal store, the downloads.
"""

from __future__ import annotations

import logging
import threading
from pathlib import Path

from flask import Blueprint, abort, jsonify, render_template, request, send_file, url_for

from common.store import ArtifactMissing, Store
from common.web.bench import check_fragment_id

from .station import answers_in_json, station

log = logging.getLogger("tessera.web")

# its JSON routes answer {"error": ...} like the rest of the archive: 404, 500 for a face that cannot
# be read, 507 for tiles the storage refuses (answers_in_json)
bp = answers_in_json(Blueprint("fragment", __name__))

#: the viewer's scripts and shaders
VIEWER_FOLDER = Path(__file__).resolve().parent / "static" / "viewer"
#: the viewer's shader files (in :data:`VIEWER_FOLDER`), carried in the page (no request of their own)
SHADER_FILES = ("tile.vert", "common.glsl", "albedo.frag", "lambertian.frag", "raking.frag", "specular.frag",
                "normal_unsharp.frag", "exaggerated.frag", "mean_curvature.frag")

#: relight caches whose coarse levels are being cut in the background -> set when done
_cutting: dict[str, threading.Event] = {}
_cutting_lock = threading.Lock()


def _cut_coarse_levels(cache) -> None:
    """The first time a face is opened here, cut its coarse levels (:meth:`RelightCache.cut` from
    :meth:`RelightCache.whole_from`) in one background pass: one read of the face instead of one per
    tile; the tile requests of those levels wait for it."""
    level = cache.whole_from()
    with _cutting_lock:
        if level is None or cache.folder in _cutting:
            return
        done = _cutting[cache.folder] = threading.Event()

    def run():
        try:
            cache.cut(min_level=level)
        except Exception:   # the tile requests cut what they need themselves
            log.exception("cutting the relight tiles of %s", cache.rgbn_relpath)
        finally:
            done.set()
    threading.Thread(target=run, name=f"relight-cut {cache.folder}", daemon=True).start()


def shader_sources() -> dict[str, str]:
    """``{file name: source}`` of :data:`SHADER_FILES`, read as they are now (a few kB): the page
    carries them in a JSON data block, so the viewer compiles its first style without waiting for
    nine requests over the browser's six connections."""
    return {name: (VIEWER_FOLDER / name).read_text() for name in SHADER_FILES}


def _wait_for_cut(cache, level: int, tiles) -> None:
    """If the background pass (:func:`_cut_coarse_levels`) writes ``level``, wait until it has
    written ``tiles`` ``[(row, col)]`` (it goes coarsest first) rather than cut them here too: two
    computations of one tile would race for the CPU and the first picture would wait for both."""
    cutting = _cutting.get(cache.folder)
    if cutting is None or level < (cache.whole_from() or level + 1):
        return
    targets = [cache.store.path(cache.tile_relpath(level, r, c)) for r, c in tiles]
    while not cutting.is_set() and not all(p.is_file() for p in targets):
        cutting.wait(0.05)


def _fid(fid: str) -> str:
    try:
        return check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))


def _store() -> Store:
    return Store(station().store_root, create=False)


def _faces(fid: str) -> dict[str, str]:
    from common.imports.export import latest_faces

    return latest_faces(_store(), fid)


def _cache(fid: str, stem: str):
    """The relight cache of face artifact ``fragments/<fid>/rgbn/<stem>.h5`` (404 if not there)."""
    from common.web.relight import RelightCache

    if "/" in stem or stem.startswith(".") or "-" not in stem:
        abort(404, f"no face {stem!r}")
    rel = f"fragments/{fid}/rgbn/{stem}.h5"
    store = _store()
    if not store.exists(rel):
        abort(404, f"fragment {fid} has no face artifact {stem}")
    return RelightCache(store, rel)


def _face_list(fid: str) -> list[dict]:
    """``[{face, artifact, relight}]``: each face's newest RGBN artifact and its relight API, the
    front first, then the back, then any other face."""
    from common.imports.export import face_order

    out = []
    for face, rel in sorted(_faces(fid).items(), key=lambda kv: face_order(kv[0])):
        stem = rel.rsplit("/", 1)[1][:-3]
        out.append({"face": face, "artifact": rel,
                    "relight": url_for("fragment.params", fid=fid, stem=stem).rsplit("/", 1)[0]})
    return out


@bp.get("/fragments/<fid>")
def page(fid):
    """The page. Its faces are in it (``data-faces``), with the parameters of the face it opens
    when they are computed already, and the browser is told to fetch that face's one-tile top
    level at once (``<link rel="preload">``): the first picture needs no other round trip."""
    import json

    from common.web.relight import RelightCache

    fid = _fid(fid)
    faces = _face_list(fid)
    preload = []
    first = next((f for f in faces if f["face"] == request.args.get("face")), faces[0] if faces else None)
    if first is not None:
        cache = RelightCache(_store(), first["artifact"])
        stored = _store().path(f"{cache.folder}/params.json")
        if stored.is_file():
            first["params"] = json.loads(stored.read_text())
            _cut_coarse_levels(cache)   # returns at once when they are cut (or being cut) already
            preload.append(f"{first['relight']}/tiles/{len(first['params']['levels']) - 1}/0_0")
    return render_template("fragment.html", page="fragment", fragment=fid, faces=json.dumps(faces),
                           preload=preload, shaders=shader_sources())


@bp.get("/api/fragments/<fid>")
def fragment(fid):
    """Faces (with their relight API), proposals, confirmed joins and downloads of one fragment."""
    fid = _fid(fid)
    out_faces = _face_list(fid)
    if not out_faces:
        abort(404, f"fragment {fid} has no RGBN face on storage yet")
    proposals = []
    review = station().review
    if review is not None:
        proposals = review.ranked(fid, limit=50)
    for p in proposals:
        other = p["fragment_b"] if p["fragment_a"] == fid else p["fragment_a"]
        p["other"] = other
        p["other_url"] = url_for("fragment.page", fid=other)
        p["review_url"] = url_for("review.page", fragment=fid)
    # the page lists confirmed joins and pending proposals; a rejected pair is neither
    return jsonify(fragment=fid, faces=out_faces,
                   proposals=[p for p in proposals if p.get("status") == "pending"],
                   joins=[p for p in proposals if p.get("status") == "confirmed"],
                   proposals_available=review is not None, **_related(fid))


def _related(fid: str) -> dict:
    """URLs of the archive's other APIs about this fragment, when the app has them: its downloads
    (``tessera export``'s files) and its catalogue row (metadata, edit history)."""
    from flask import current_app

    out = {}
    for key, endpoint in (("downloads", "downloads.listing"), ("catalogue", "catalogue.fragment")):
        if endpoint in current_app.view_functions:
            out[key] = url_for(endpoint, fid=fid)
    return out


@bp.get("/api/fragments/<fid>/relight/<stem>/params.json")
def params(fid, stem):
    """The face's relighting parameters (:func:`common.web.relight.face_params`), computed once."""
    fid = _fid(fid)
    cache = _cache(fid, stem)
    try:
        params = cache.params()
    except ArtifactMissing as exc:   # gone since the check; a face that cannot be read is a 500
        abort(404, str(exc))
    _cut_coarse_levels(cache)
    return jsonify(params)


@bp.get("/api/fragments/<fid>/relight/<stem>/tiles/<int:level>/<tile>")
def tile(fid, stem, level, tile):
    """One tile of the face's relighting fields (gzip; the format of :mod:`common.web.relight`),
    computed on first request and kept on storage; immutable (the URL names the artifact)."""
    fid = _fid(fid)
    try:
        row, col = (int(x) for x in tile.split("_"))
    except ValueError:
        abort(404, f"no tile {tile!r} (expected <row>_<column>)")
    cache = _cache(fid, stem)
    _wait_for_cut(cache, level, [(row, col)])
    try:
        path = cache.tile_path(level, row, col)
    except ValueError as exc:
        abort(404, str(exc))
    except ArtifactMissing as exc:   # gone since the check; a face that cannot be read is a 500
        abort(404, str(exc))
    resp = send_file(path, mimetype="application/octet-stream", conditional=False, etag=False)
    resp.headers["Content-Encoding"] = "gzip"
    resp.headers["Cache-Control"] = "public, max-age=31536000, immutable"
    return resp


@bp.get("/api/fragments/<fid>/relight/<stem>/auto")
def auto(fid, stem):
    """The contrast the offline style's "auto" picks for the viewer's parameters (``style`` and
    ``values`` as JSON in the query), measured on the face's overview level."""
    import json

    from common.web.relight import auto_contrast, overview_level

    fid = _fid(fid)
    style = request.args.get("style", "")
    try:
        values = json.loads(request.args.get("values", "{}"))
    except ValueError:
        abort(400, "values must be a JSON object of the style's parameters")
    if not isinstance(values, dict):
        abort(400, "values must be a JSON object of the style's parameters")
    cache = _cache(fid, stem)
    params = cache.params()
    if not params["has_normals"] and style != "albedo":
        abort(400, f"face {stem} has no normals (colour only): only the albedo style applies")
    level = overview_level(params)
    _wait_for_cut(cache, level, cache.tiles_of(level))
    try:
        image = cache.level_image(level)
        return jsonify(style=style, level=level, resolved=auto_contrast(image, style, values, params, level=level))
    except (ValueError, TypeError) as exc:
        abort(400, str(exc))
