"""The archive's catalogue (``/fragments``): every fragment, searchable, with metadata edits.

The page reads the catalogue's index (:class:`common.web.catalogue.Catalogue`, kept current from
the event feed); an edit is sent to the broker as a ``fragment.annotated`` event through the
outbox and shows as *sent* until the feed brings it back and the catalogue has applied it.
"""

from __future__ import annotations

import logging

from flask import Blueprint, abort, jsonify, render_template, request

from common.messages import new_message
from common.web.bench import check_fragment_id
from common.web.catalogue import COLOUR_FAMILIES, FIELDS, STAGE_ORDER, check_changes

from .auth import body, who, writes
from .station import answers_in_json, requires, station, submit_or_503

log = logging.getLogger("tessera.web")

bp = answers_in_json(Blueprint("catalogue", __name__))

needs_catalogue = requires("catalogue", "the catalogue is not available on this station")


def _fid(fid: str) -> str:
    try:
        return check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))


@bp.get("/fragments")
def page():
    return render_template("catalogue.html", page="catalogue", families=COLOUR_FAMILIES,
                           states=("waiting", "failed") + STAGE_ORDER, fields=FIELDS)


@bp.get("/api/catalogue")
@needs_catalogue
def listing():
    st = station()
    a = request.args
    try:
        out = st.catalogue.query(text=a.get("q", ""), state=a.get("state", ""), colour=a.get("colour", ""),
                                 joins=a.get("joins", ""), page=a.get("page", 1, type=int),
                                 per_page=a.get("per_page", 50, type=int))
    except ValueError as exc:
        abort(400, str(exc))
    out["counts"] = st.catalogue.counts()
    out["feed"] = {"following": st.feed is not None, "error": st.feed.error if st.feed is not None else ""}
    return jsonify(out)


@bp.get("/api/catalogue/<fid>")
@needs_catalogue
def fragment(fid):
    st = station()
    fid = _fid(fid)
    row = st.catalogue.get(fid)
    if row is None:
        abort(404, f"fragment {fid} is not in the catalogue")
    applied = {h["uid"] for h in row["history"]}
    row["sent"] = [e for e in st.sent_edits if e["fragment"] == fid and e["uid"] not in applied]
    return jsonify(row)


@bp.get("/api/catalogue/<fid>/thumb.png")
@needs_catalogue
def thumbnail(fid):
    png = station().catalogue.thumbnail(_fid(fid))
    if png is None:
        abort(404, f"fragment {fid} has no thumbnail")
    return png, 200, {"Content-Type": "image/png", "Cache-Control": "private, max-age=60"}


@bp.post("/api/catalogue/<fid>/metadata")
@writes
@needs_catalogue
def edit(fid):
    st = station()
    fid = _fid(fid)
    row = st.catalogue.get(fid)
    if row is None:
        abort(404, f"fragment {fid} is not in the catalogue")
    try:
        changes = check_changes(body().get("changes"))
    except ValueError as exc:
        return jsonify(error=str(exc)), 400
    changes = {k: v for k, v in changes.items() if v != row[k]}
    if not changes:
        return jsonify(error="nothing changed"), 400
    by = who()
    msg = new_message("fragment.annotated", fragment=fid, changes=changes, by=by,
                      previous={k: row[k] for k in changes})
    delivered = submit_or_503(msg, "edit")
    entry = {"fragment": fid, "uid": msg["uid"], "time": msg["time"], "by": by, "changes": changes,
             "delivered": delivered}
    st.sent_edits.appendleft(entry)
    if st.feed is not None and delivered:
        try:
            st.feed.poll(blocking=False)   # apply it now rather than at the next round (unless one is running)
        except Exception as exc:
            log.info("event feed not polled after an edit: %s", exc)
    return jsonify(sent=entry)
