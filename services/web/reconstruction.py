"""The reconstruction page (``/reconstruction``): confirmed joins assembled into clusters, live.

The pose graph is :mod:`common.matching.reconstruction`; this blueprint feeds it the proposal store
(read-only, through the review data) and each fragment's centre, and serves:

* ``GET /reconstruction`` — the page: each cluster drawn at its solved poses (SVG over thumbnails),
  conflicting loops and given-up joins in red, the next joins along its open edges as ghosts at the
  pose they would take, and where a newcomer fits one of the cluster's corners that fit too (docked against
  the whole cluster: a background job, cached, whose results arrive as a change), export links;
* ``GET /api/reconstruction`` — the reconstruction as JSON (the ``tessera.reconstruction`` document,
  plus display data: thumbnails and sizes, verdicts seen on the event feed but not yet recorded);
* ``GET /api/reconstruction/changes?after=SIG`` — long poll: answers when the verdicts or pending
  proposals change (or a ``match.verified`` arrives on the feed), or after ``long_poll_s``;
* ``GET /api/reconstruction/thumb/<fid>.png`` — a fragment's front albedo, small, alpha = mask;
* ``GET /api/reconstruction/<root>/composite.png|.tif`` and ``/api/reconstruction/poses.json`` — the
  exports (8-bit PNG, 16-bit TIFF, JSON). Everything here reads; nothing writes.
"""

from __future__ import annotations

import collections
import io
import logging
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np
from flask import Blueprint, abort, current_app, jsonify, render_template, request, send_file, url_for

from common.messages import to_json, verdict_of
from common.web.bench import check_fragment_id

from .station import EXTENSION, requires, station

log = logging.getLogger("tessera.web")

bp = Blueprint("reconstruction", __name__)

#: key of the page's live state in ``app.extensions``
LIVE = "tessera.reconstruction"
#: longest side of a fragment thumbnail (px) and of an exported composite (px, unless asked smaller)
THUMB_PX = 320
EXPORT_MAX_SIDE_PX = 8192
EXPORT_DEFAULT_SIDE_PX = 4096

needs_proposals = requires("review", "the proposal store is not available on this station")


class _Live:
    """Per app: fragment summaries by artifact, the last reconstruction, verdicts seen on the feed."""

    def __init__(self):
        self.lock = threading.Lock()
        self.compute_lock = threading.Lock()
        self.summaries: dict[str, dict] = {}
        self.result: tuple | None = None         # (signature, payload)
        self.arriving: collections.deque = collections.deque(maxlen=200)
        self.feed_seen = 0
        # docking next joins against their clusters (0.1-0.3 s CPU each): made in a background thread, kept
        self.docked: dict = {}                 # reconstruction.dock_key -> (pose, faced)
        self.pieces: dict = {}                 # (feature table path, sha256) -> (contour_mm, paint field)
        self.dock_round = 0                    # bumped when dockings land: part of the signature
        self.dock_tried: frozenset = frozenset()
        self.dock_thread: threading.Thread | None = None

    def on_verdict(self, event: dict, seq: int) -> None:
        """Feed subscriber: a ``match.verified`` (recorded by the matcher shortly after)."""
        with self.lock:
            self.arriving.append({"fragment_a": min(event["fragment"], event["other"]),
                                  "fragment_b": max(event["fragment"], event["other"]),
                                  "verdict": verdict_of(event.get("verdict")), "by": event.get("by"), "time": event.get("time"),
                                  "uid": event.get("uid"), "seq": seq})
            self.feed_seen += 1


@bp.record_once
def _follow_feed(state) -> None:
    live = state.app.extensions.setdefault(LIVE, _Live())
    st = state.app.extensions.get(EXTENSION)
    if st is not None and st.feed is not None:
        st.feed.subscribe(["match.verified"], live.on_verdict)


def _live() -> _Live:
    return current_app.extensions.setdefault(LIVE, _Live())


def _signature() -> str:
    """Changes whenever a verdict is recorded, a pending proposal changes, or the feed brings a verdict."""
    def read(db):
        v = db._db.execute("SELECT COUNT(*), COALESCE(MAX(id), 0) FROM verdicts").fetchone()
        p = db._db.execute("SELECT COUNT(*), COALESCE(MAX(updated), 0) FROM proposals WHERE status='pending'").fetchone()
        return f"{v[0]}.{v[1]}.{p[0]}.{p[1]:.3f}"
    live = _live()
    return f"{station().review._read(read, 'none')}.{live.feed_seen}.{live.dock_round}"


def _summary(store, fid: str) -> dict | None:
    """Centre, size and thumbnail of a fragment's newest front image, cached per artifact (None if absent)."""
    from common.imports.export import latest_faces
    from common.matching.reconstruction import mask_centre_mm
    from common.rgbn.image import load_rgbn
    from common.rgbn.io import linear_to_srgb
    from common.store import ArtifactError
    from common.web.compose import outline_mm

    rel = latest_faces(store, fid).get("front")
    if rel is None:
        return None
    live = _live()
    with live.lock:
        if rel in live.summaries:
            return live.summaries[rel]
    try:
        img = load_rgbn(store, rel)
        centre = mask_centre_mm(img)
    except (ArtifactError, OSError, ValueError) as exc:
        log.warning("reconstruction: %s unreadable: %s", rel, exc)
        return None
    h, w = img.mask.shape
    s = min(1.0, THUMB_PX / max(h, w))
    size = (max(1, round(w * s)), max(1, round(h * s)))
    rgb = (linear_to_srgb(cv2.resize(img.albedo, size, interpolation=cv2.INTER_AREA)) * 255 + 0.5).astype(np.uint8)
    alpha = cv2.resize(img.mask.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    rgba = np.dstack([rgb, (alpha * 255 + 0.5).astype(np.uint8)])
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    # the picture spans pixel edges: from -pixel/2 to (W - 1/2) pixels in the fragment frame (mm)
    out = {"fragment": fid, "artifact": rel, "dpi": img.dpi, "pixel_mm": img.pixel_mm, "centre_mm": list(centre),
           "x_mm": -0.5 * img.pixel_mm, "y_mm": -0.5 * img.pixel_mm, "width_mm": w * img.pixel_mm,
           "height_mm": h * img.pixel_mm, "outline_mm": outline_mm(img.mask, img.pixel_mm),
           "png": png.tobytes() if ok else b""}
    with live.lock:
        live.summaries[rel] = out
    return out


def _dock_in_background(st, live: _Live, clusters: list, nexts: dict, todo: frozenset) -> bool:
    """Start docking the next joins in ``todo`` (keys of :func:`~common.matching.reconstruction.dock_key`) against
    their clusters, unless a docking runs or these were tried already; True while one runs. Its dockings land in
    ``live.docked`` and bump ``live.dock_round``, which changes the signature: the page reloads and shows them."""
    from common.matching.reconstruction import dock_key, dock_next_joins, front_pieces
    from common.store import Store

    def dock():
        found = {}
        try:
            mine = [c for c in clusters if any(dock_key(c, d["member"], d["newcomer"]) in todo for d in nexts[c.id])]
            wanted = {f for c in mine for f in c.fragments} | {d["newcomer"] for c in mine for d in nexts[c.id]}
            tables = st.review._read(lambda db: db.fragments(face="front"), [])
            with live.lock:
                found = dict(live.docked)
            if len(live.pieces) > 4096:         # only this thread touches the pieces; a long-lived page forgets old ones
                live.pieces.clear()
            pieces, unread = front_pieces(Store(st.store_root, create=False), tables, wanted, cache=live.pieces)
            for f, why in unread.items():
                log.info("reconstruction: %s not docked against its cluster, no fit offered (%s)", f, why)
            for c in mine:
                dock_next_joins(c, nexts[c.id], pieces, cache=found)
        except Exception:   # a bug or a bad table must not kill the page: the proposals' poses stay
            log.exception("reconstruction: docking the next joins against their clusters failed")
        finally:
            with live.lock:
                if len(found) > 20000:         # poses of clusters long since grown
                    found = {}
                live.docked.update(found)
                live.dock_round += 1

    with live.lock:
        running = live.dock_thread is not None and live.dock_thread.is_alive()
        if running or not todo or todo <= live.dock_tried:
            return running
        live.dock_tried = todo
        live.dock_thread = threading.Thread(target=dock, name="tessera-reconstruction-dock", daemon=True)
        live.dock_thread.start()
        return True


def _reconstruction() -> dict:
    """The solved reconstruction and its display data, recomputed only when the signature changes."""
    from common.matching.reconstruction import (confirmed_joins, dock_key, dock_next_joins, reconstruct,
                                                reconstruction_document)
    from common.store import Store

    st, live = station(), _live()
    sig = _signature()
    with live.lock:
        if live.result is not None and live.result[0] == sig:
            return live.result[1]
    with live.compute_lock:
        with live.lock:
            if live.result is not None and live.result[0] == sig:
                return live.result[1]
        store = Store(st.store_root, create=False)
        joins = st.review._read(lambda db: confirmed_joins(db)[0], [])
        summaries = {}
        for f in sorted({f for j in joins for f in j.pair}):
            summaries[f] = _summary(store, f)
        dpi = {f: s["dpi"] for f, s in summaries.items() if s}
        rec = st.review._read(lambda db: reconstruct(
            db, centres_mm={f: s["centre_mm"] for f, s in summaries.items() if s}, dpi=dpi), None)
        if rec is None:
            payload = {"signature": sig, "document": None, "fragments": {}, "arriving": [], "missing": [],
                       "docking": False}
        else:
            # newcomers docked against their clusters before carry their fit; the others are docked meanwhile
            with live.lock:
                docked = dict(live.docked)
            nexts = {c.id: dock_next_joins(c, rec["next"][c.id], {}, cache=docked) for c in rec["clusters"]}
            todo = frozenset(dock_key(c, d["member"], d["newcomer"]) for c in rec["clusters"]
                             for d in nexts[c.id]) - docked.keys()
            docking = _dock_in_background(st, live, rec["clusters"], nexts, todo)
            for nxt in nexts.values():
                for d in nxt:
                    if d["newcomer"] not in summaries:
                        summaries[d["newcomer"]] = _summary(store, d["newcomer"])
            with live.lock:
                seen = list(live.arriving)
            # a verdict on the feed is arriving until the matcher has recorded that message
            recorded = st.review._read(lambda db: {r[0] for r in db._db.execute(
                "SELECT message_uid FROM verdicts WHERE message_uid IS NOT NULL AND time >= ?",
                (min((v["time"] or 0 for v in seen), default=0) - 60,))}, set())
            arriving = [v for v in seen if v["verdict"] == "confirmed" and v["uid"] not in recorded]
            doc = reconstruction_document(rec["clusters"], unposed=rec["unposed"], next_by_cluster=nexts, dpi=dpi)
            for c in doc["clusters"]:
                root = c["root"]
                c["exports"] = {"png": url_for("reconstruction.composite", root=root, ext="png"),
                                "tiff": url_for("reconstruction.composite", root=root, ext="tif")}
            payload = {"signature": sig, "document": doc, "arriving": arriving, "docking": docking,
                       "missing": sorted(f for f, s in summaries.items() if s is None),
                       "fragments": {f: {k: v for k, v in s.items() if k not in ("png", "artifact")} |
                                     {"thumb": url_for("reconstruction.thumb", fid=f)}
                                     for f, s in summaries.items() if s}}
        with live.lock:
            live.result = (sig, payload)
        return payload


def cluster_fit(proposal: dict) -> tuple[dict | None, bool]:
    """Where a pending proposal's newcomer fits into a corner of its confirmed cluster, as this page shows it:
    ``({angle_deg, tx_mm, ty_mm, cluster, faces}, docking)`` with the pose as fragment B in fragment A's frame
    (the proposal's convention), or ``(None, docking)``; ``docking`` says whether the background docking is still
    running (the fit may come). The review page offers a proposal this pose (docs/web.md)."""
    from common.matching.reconstruction import fit_as_proposal_pose

    def triple(pose):
        return (pose["angle_deg"], pose["tx_mm"], pose["ty_mm"])

    data = _reconstruction()
    for c in (data["document"] or {}).get("clusters", []):
        for n in c["next_joins"]:
            if n["proposal"] != proposal["id"] or not n.get("fit"):
                continue
            member = next(f for f in c["fragments"] if f["fragment"] == n["member"])
            angle, tx, ty = fit_as_proposal_pose(triple(member), triple(n["fit"]), n["member"], proposal["fragment_a"])
            return {"angle_deg": angle, "tx_mm": tx, "ty_mm": ty, "cluster": c["id"], "faces": n["faces"]}, \
                data["docking"]
    return None, data["docking"]


@bp.get("/reconstruction")
def page():
    return render_template("reconstruction.html", page="reconstruction")


@bp.get("/api/reconstruction")
@needs_proposals
def reconstruction():
    return jsonify(_reconstruction())


@bp.get("/api/reconstruction/changes")
@needs_proposals
def changes():
    after = request.args.get("after", "")
    deadline = time.monotonic() + float(station().settings["long_poll_s"])
    sig = _signature()
    while sig == after and time.monotonic() < deadline:
        time.sleep(0.25)
        sig = _signature()
    return jsonify(signature=sig, changed=sig != after)


@bp.get("/api/reconstruction/thumb/<fid>.png")
def thumb(fid):
    from common.store import Store

    try:
        fid = check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))
    s = _summary(Store(station().store_root, create=False), fid)
    if s is None or not s["png"]:
        return jsonify(error=f"fragment {fid} has no readable front image"), 404
    return s["png"], 200, {"Content-Type": "image/png", "Cache-Control": "private, max-age=300"}


@bp.get("/api/reconstruction/poses.json")
@needs_proposals
def poses():
    doc = _reconstruction()["document"]
    if doc is None:
        return jsonify(error="no proposal store yet: nothing is confirmed"), 404
    body = to_json(doc, indent=2) + "\n"   # strict, as tessera reconstruct writes it: NaN/±inf as null
    return body, 200, {"Content-Type": "application/json",
                       "Content-Disposition": 'attachment; filename="reconstruction.json"'}


@bp.get("/api/reconstruction/<root>/composite.<ext>")
@needs_proposals
def composite(root, ext):
    from common.matching.reconstruction import Cluster, compose_cluster, front_images
    from common.rgbn.io import linear_to_srgb, write_image
    from common.store import Store

    if ext not in ("png", "tif"):
        abort(404)
    data = _reconstruction()
    cluster = next((c for c in (data["document"] or {}).get("clusters", []) if c["root"] == root), None)
    if cluster is None:
        return jsonify(error=f"no cluster with root fragment {root!r} (it may have merged: reload the page)"), 404
    side = min(max(request.args.get("max_side", EXPORT_DEFAULT_SIDE_PX, type=int), 64), EXPORT_MAX_SIDE_PX)
    ids = [f["fragment"] for f in cluster["fragments"]]
    images, missing = front_images(Store(station().store_root, create=False), ids)
    if missing:
        return jsonify(error="; ".join(f"{f}: {why}" for f, why in missing.items())), 404
    solved = Cluster(id=cluster["id"], root=root, fragments=ids, joins=[],
                     poses={f["fragment"]: (f["angle_deg"], f["tx_mm"], f["ty_mm"]) for f in cluster["fragments"]})
    comp = compose_cluster(solved, images, max_side_px=side)
    with tempfile.TemporaryDirectory(prefix="tessera-composite-") as tmp:
        path = write_image(Path(tmp) / f"cluster-{root}.{ext}", linear_to_srgb(comp["albedo"]),
                           bits=8 if ext == "png" else 16, alpha=comp["alpha"], dpi=comp["dpi"])
        payload = io.BytesIO(path.read_bytes())
    return send_file(payload, mimetype="image/png" if ext == "png" else "image/tiff", as_attachment=True,
                     download_name=f"cluster-{root}.{ext}")
