"""Tile pyramids of a fragment's faces (albedo, normal map, renders) for deep zoom and relighting.

URLs (``common.web.tiles`` cuts and caches the pyramids; see ``docs/web.md``):

* ``GET /api/tiles/<fid>`` — the fragment's faces and the pyramid URL of each layer the face has (cuts
  nothing; a colour-only face lists no ``normals``);
* ``GET /api/tiles/<fid>/<face>/<layer>`` — ``pyramid.json`` of the face's newest source (cut on
  the first request) plus ``tiles``, the URL template of its tiles; ``layer`` is ``albedo``,
  ``normals`` (faces with normals) or ``render-<recipe>``;
* ``GET /api/tiles/<fid>/<pyramid>/<layer>/<level>/<col>_<row>.png`` — one tile. ``<pyramid>`` names
  the source artifact (``rgbn-front-<key>``), so a tile URL never changes content: cached for a year;
* ``GET /dzi/<fid>~<face>~<layer>.dzi`` and ``/dzi/<fid>~<face>~<layer>_files/<level>/<col>_<row>.png`` —
  the same pyramid as Deep Zoom (level numbers counted from the 1 x 1 level), for OpenSeadragon
  and openlime's ``deepzoom`` layout (a BRDF layer with ``kd`` = albedo, ``normals`` = normals).
"""

from __future__ import annotations

from flask import Blueprint, Response, abort, jsonify, send_file, url_for

from common.store import ArtifactMissing
from common.web.bench import check_fragment_id
from common.web.tiles import TILES_VERSION, dzi_tile, dzi_xml, encode_png, face_sources, pyramid_folder

from .station import answers_in_json, station

bp = answers_in_json(Blueprint("tiles", __name__))


def fragment_or_404(fid: str) -> dict:
    """``face_sources`` of a valid fragment id that has at least one face on storage (else 400/404)."""
    try:
        fid = check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))
    faces = face_sources(station().tiles.store, fid)
    if not faces:
        abort(404, f"fragment {fid} has no face on storage")
    return faces


def face_layers(source: dict) -> list[str]:
    """The layers a face has (what the tile list offers): ``albedo``, ``normals`` unless it is colour-only,
    ``render-<recipe>`` per illustration."""
    return ["albedo"] + (["normals"] if source["normals"] else []) + [f"render-{r}" for r in source["renders"]]


def layer_source(faces: dict, face: str, layer: str) -> str:
    """The artifact a layer of a face is cut from (404 naming what exists otherwise)."""
    if face not in faces:
        abort(404, f"no face {face!r} (faces: {', '.join(faces)})")
    known = face_layers(faces[face])
    if layer in known and layer in ("albedo", "normals"):
        return faces[face]["rgbn"]
    recipe = layer.removeprefix("render-")
    if layer in known and layer.startswith("render-"):
        return faces[face]["renders"][recipe]
    why = " (a colour-only face has no normals)" if layer == "normals" else ""
    abort(404, f"no layer {layer!r} for face {face}{why} (layers: {', '.join(known)})")


def pyramid_info(fid: str, face: str, layer: str) -> dict:
    """``pyramid.json`` of a layer with ``tiles`` (URL template) and ``layer``; cuts it if needed."""
    source = layer_source(fragment_or_404(fid), face, layer)
    info = dict(station().tiles.pyramid(source))
    stored = "render" if layer.startswith("render-") else layer
    if stored not in info["layers"]:
        abort(404, f"face {face} of {fid} has no {layer} (colour-only data has no normals)")
    name = pyramid_folder(source).rsplit("/", 1)[1]
    template = url_for("tiles.tile", fid=fid, pyramid=name, layer=stored, level=0, col=0, row=0)
    info.update(fragment=fid, face=face, layer=layer, pyramid=name,
                tiles=template.replace("/0/0_0.png", "/{level}/{col}_{row}.png"))
    return info


@bp.get("/api/tiles/<fid>")
def faces(fid):
    out = {}
    for face, src in fragment_or_404(fid).items():   # only the layers the face has: no normals for colour-only
        out[face] = {"source": src["rgbn"],
                     "layers": {name: url_for("tiles.pyramid", fid=fid, face=face, layer=name)
                                for name in face_layers(src)}}
    return jsonify(fragment=fid, faces=out, version=TILES_VERSION)


@bp.get("/api/tiles/<fid>/<face>/<layer>")
def pyramid(fid, face, layer):
    return jsonify(pyramid_info(fid, face, layer))


@bp.get("/api/tiles/<fid>/<pyramid>/<layer>/<int:level>/<int:col>_<int:row>.png")
def tile(fid, pyramid, layer, level, col, row):
    try:
        fid = check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))
    kind, _, stem = pyramid.partition("-")
    if kind not in ("rgbn", "render") or not stem.endswith(f"-t{TILES_VERSION}"):
        abort(404, f"no pyramid {pyramid!r}")
    source = f"fragments/{fid}/{'rgbn' if kind == 'rgbn' else 'renders'}/{stem.rsplit('-t', 1)[0]}.h5"
    try:
        path = station().tiles.tile_path(source, layer, level, col, row)
    except (LookupError, ValueError) as exc:
        abort(404, str(exc))
    except ArtifactMissing:
        abort(404, f"no artifact {source}")
    resp = send_file(path, mimetype="image/png", max_age=365 * 86400, conditional=True)
    resp.headers["Cache-Control"] = "public, max-age=31536000, immutable"
    return resp


# -- Deep Zoom (OpenSeadragon, openlime's "deepzoom" layout) -------------------------------------
def _dzi_source(identifier: str) -> tuple[dict, str, str]:
    from common.web.iiif import IIIFError, split_image_id

    try:
        fid, face, layer = split_image_id(identifier)
    except IIIFError as exc:
        abort(404, str(exc))
    info = pyramid_info(fid, face, layer)
    return info, info["source"]["path"], "render" if layer.startswith("render-") else layer


@bp.get("/dzi/<identifier>.dzi")
def dzi(identifier):
    info, _, _ = _dzi_source(identifier)
    resp = Response(dzi_xml(info), mimetype="application/xml")
    resp.headers["Access-Control-Allow-Origin"] = "*"
    return resp


@bp.get("/dzi/<identifier>_files/<int:level>/<int:col>_<int:row>.png")
def dzi_tile_png(identifier, level, col, row):
    info, source, layer = _dzi_source(identifier)
    try:
        rgba = dzi_tile(station().tiles, source, layer, level, col, row)
    except LookupError as exc:
        abort(404, str(exc))
    resp = Response(encode_png(rgba), mimetype="image/png")
    resp.headers["Cache-Control"] = "public, max-age=600"
    resp.headers["Access-Control-Allow-Origin"] = "*"
    return resp
