"""Downloads of a fragment: the files ``tessera export`` writes (normal map, albedo, renders, metadata).

* ``GET /api/downloads/<fid>`` — the list of files (name, bytes, URL) and the URL of a zip of them
  all; the first request exports them (:func:`common.imports.export.export_fragment`) into
  ``fragments/<id>/downloads/<key>/`` on storage, keyed by the artifacts they come from, so later
  requests and other viewers read the same files;
* ``GET /api/downloads/<fid>/<key>/<name>`` — one file; ``GET /api/downloads/<fid>/<key>.zip`` — all.
"""

from __future__ import annotations

import threading

from flask import Blueprint, abort, jsonify, send_file, url_for

from common.web.downloads import export_folder, export_key
from common.store import Store

from .station import answers_in_json, station
from .tiles import fragment_or_404

bp = answers_in_json(Blueprint("downloads", __name__))
_lock = threading.Lock()   # one export at a time in this process (an export reads whole faces)


def _store() -> Store:
    return station().tiles.store


@bp.get("/api/downloads/<fid>")
def listing(fid):
    fragment_or_404(fid)
    store = _store()
    with _lock:
        folder, key = export_folder(store, fid)
    files = sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
    return jsonify(fragment=fid, key=key, zip=url_for("downloads.archive", fid=fid, key=key),
                   files=[{"name": p.name, "bytes": p.stat().st_size,
                           "url": url_for("downloads.file", fid=fid, key=key, name=p.name)} for p in files])


def _folder(fid: str, key: str):
    fragment_or_404(fid)
    if key != export_key(_store(), fid):
        abort(404, f"no download {key!r} of {fid} (its faces changed: ask /api/downloads/{fid} again)")
    with _lock:
        folder, _ = export_folder(_store(), fid)
    return folder


@bp.get("/api/downloads/<fid>/<key>/<name>")
def file(fid, key, name):
    path = _folder(fid, key) / name
    if name.startswith(".") or "/" in name or not path.is_file():
        abort(404, f"no file {name!r} in the download of {fid}")
    resp = send_file(path, as_attachment=True, download_name=f"{fid}-{name}", max_age=365 * 86400)
    resp.headers["Cache-Control"] = "public, max-age=31536000, immutable"
    return resp


@bp.get("/api/downloads/<fid>/<key>.zip")
def archive(fid, key):
    from common.web.downloads import export_zip

    folder = _folder(fid, key)
    with _lock:
        path = export_zip(folder, fid)
    resp = send_file(path, mimetype="application/zip", as_attachment=True, download_name=f"{fid}.zip",
                     max_age=365 * 86400)
    resp.headers["Cache-Control"] = "public, max-age=31536000, immutable"
    return resp
