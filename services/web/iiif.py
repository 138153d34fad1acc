"""IIIF endpoints: Image API 3.0 (level 2) over the cached tiles, Presentation 3.0 manifests.

* ``GET /iiif/image/<fid>~<face>~<layer>/info.json`` and
  ``GET /iiif/image/<fid>~<face>~<layer>/<region>/<size>/<rotation>/<quality>.<format>`` —
  ``layer`` is ``albedo``, ``normals`` or ``render-<recipe>`` (:mod:`common.web.iiif`);
* ``GET /iiif/presentation/<fid>/manifest`` — the fragment's manifest: a canvas per face.

Reading is open and cross-origin (``Access-Control-Allow-Origin: *``), so museum viewers on
other sites (Mirador, Universal Viewer, OpenSeadragon) can load them.
"""

from __future__ import annotations

from flask import Blueprint, Response, jsonify, redirect, request, url_for

from common.web import iiif

from .station import answers_in_json, station
from .tiles import fragment_or_404, pyramid_info

bp = answers_in_json(Blueprint("iiif", __name__))


@bp.errorhandler(iiif.IIIFError)
def iiif_error(exc: iiif.IIIFError):
    return jsonify(error=str(exc)), exc.status


@bp.after_request
def cross_origin(resp):
    """CORS on every answer (Image API 3.0 §7.1), the preflight (OPTIONS) pattern included: any
    origin may read, with GET or HEAD, sending any header it asks for (no credentials: nothing here
    is private); the Link header (profile, canonical) readable by scripts."""
    resp.headers["Access-Control-Allow-Origin"] = "*"
    resp.headers["Access-Control-Expose-Headers"] = "Link"
    if request.method == "OPTIONS":
        resp.headers["Access-Control-Allow-Methods"] = "GET, HEAD, OPTIONS"
        asked = request.headers.get("Access-Control-Request-Headers")
        if asked:
            resp.headers["Access-Control-Allow-Headers"] = asked
        resp.headers["Access-Control-Max-Age"] = "86400"
    return resp


def _base() -> str:
    return request.host_url.rstrip("/")


def _pyramid(identifier: str) -> dict:
    fid, face, layer = iiif.split_image_id(identifier)
    return pyramid_info(fid, face, layer)


@bp.get("/iiif/image/<identifier>")
def image_base(identifier):
    return redirect(url_for("iiif.info", identifier=identifier), 303)


@bp.get("/iiif/image/<identifier>/info.json")
def info(identifier):
    body = iiif.info_json(f"{_base()}/iiif/image/{identifier}", _pyramid(identifier))
    resp = jsonify(body)
    resp.headers["Content-Type"] = f'application/ld+json;profile="{iiif.IMAGE_CONTEXT}"'
    resp.headers["Link"] = f'<{iiif.PROFILE_URI}>;rel="profile"'
    return resp


@bp.get("/iiif/image/<identifier>/<region>/<size>/<rotation>/<quality_format>")
def image(identifier, region, size, rotation, quality_format):
    info = _pyramid(identifier)
    req = iiif.parse_request(region, size, rotation, quality_format, info["width"], info["height"])
    source, layer = info["source"]["path"], "render" if info["layer"].startswith("render-") else info["layer"]
    cache = station().tiles
    px = iiif.render_request(req, info["levels"],
                             lambda level, y0, y1, x0, x1: cache.region(source, layer, level, y0, y1, x0, x1))
    resp = Response(iiif.encode(iiif.finish(px, req), req.fmt), mimetype=iiif.FORMATS[req.fmt])
    resp.headers["Cache-Control"] = "public, max-age=600"
    canonical = f"{_base()}/iiif/image/{identifier}/{iiif.canonical_path(req, info['width'], info['height'])}"
    resp.headers["Link"] = f'<{iiif.PROFILE_URI}>;rel="profile", <{canonical}>;rel="canonical"'
    return resp


@bp.get("/iiif/presentation/<fid>/manifest")
def manifest(fid):
    sources = fragment_or_404(fid)
    st = station()
    faces, imported = {}, {}
    for face, src in sources.items():
        info = st.tiles.pyramid(src["rgbn"])
        layers = list(info["layers"]) + [f"render-{r}" for r in src["renders"]]
        faces[face] = {"width": info["width"], "height": info["height"], "layers": layers,
                       "pixel_mm": info["pixel_mm"]}
        imported = imported or info["metadata"]
    row = st.catalogue.get(fid) if st.catalogue is not None else None
    meta = row if row is not None else imported   # the catalogue has the edits; else the importer's
    labels = {"Inventory": meta.get("inventory", ""), "Find-spot": meta.get("find_spot", ""),
              "Context": meta.get("context", ""), "Date": meta.get("date", ""), "Notes": meta.get("notes", "")}
    body = iiif.manifest(_base(), fid, faces, labels, homepage=f"{_base()}/fragments/{fid}")
    resp = jsonify(body)
    resp.headers["Content-Type"] = f'application/ld+json;profile="{iiif.PRESENTATION_CONTEXT}"'
    return resp
