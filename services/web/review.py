"""The review page (``/review``): ranked join proposals and the conservator's verdicts.

Proposals, verdict history and pictures come from the matcher's proposal store
(:class:`common.web.review.ReviewData`); a verdict is submitted to the broker as a
``match.verified`` event through the outbox (the matcher records it).
"""

from __future__ import annotations

from flask import Blueprint, abort, jsonify, render_template, request

from common.messages import new_message
from common.web.bench import check_fragment_id

from .auth import body, who, writes
from .station import requires, station, submit_or_503

bp = Blueprint("review", __name__)

#: picture views of a proposal offered by the review page
VIEWS = ("pair-colour", "pair-relief", "joined-colour", "joined-relief")

needs_proposals = requires("review", "the proposal store is not available on this station")


@bp.get("/review")
def page():
    return render_template("review.html", page="review", fragment=request.args.get("fragment", ""))


@bp.get("/api/review/queue")
@needs_proposals
def queue():
    review = station().review
    limit = min(max(request.args.get("limit", 50, type=int), 1), 500)
    return jsonify(proposals=review.pending(limit), counts=review.counts())


@bp.get("/api/review/fragment/<fid>")
@needs_proposals
def fragment(fid):
    try:
        fid = check_fragment_id(fid)
    except ValueError as exc:
        abort(400, str(exc))
    return jsonify(fragment=fid, proposals=station().review.ranked(fid))


@bp.get("/api/review/history")
@needs_proposals
def history():
    st = station()
    recorded = st.review.history(limit=100)
    keys = {(v["fragment_a"], v["fragment_b"], v["verdict"]) for v in recorded}
    waiting = [v for v in st.sent_verdicts if (v["fragment_a"], v["fragment_b"], v["verdict"]) not in keys
               or v["time"] > max((r["time"] for r in recorded), default=0)]
    return jsonify(history=recorded, sent=list(waiting))


#: the pose adjustment a conservator may set: turn of B about its centre, degrees, and its move, mm
ADJUST_LIMITS = {"turn_deg": 360.0, "shift_x_mm": 1000.0, "shift_y_mm": 1000.0}


def _adjustment(values) -> dict:
    """The pose adjustment in ``values`` (query arguments or a JSON body's ``adjust``): each of
    :data:`ADJUST_LIMITS` a finite number within its limit (0 when absent); 400 naming the field."""
    out = {}
    for k, limit in ADJUST_LIMITS.items():
        v = values.get(k, 0.0) if values is not None else 0.0
        try:
            v = float(v)
        except (TypeError, ValueError):
            abort(400, f"{k} must be a number, got {str(v)[:40]!r}")
        if not -limit <= v <= limit:   # also refuses nan
            abort(400, f"{k} must be within ±{limit:g}, got {v}")
        out[k] = v
    return out


def _adjusted(st, pid: int, adjust: dict) -> dict | None:
    """The proposal's pose with the conservator's adjustment (None when there is none to make)."""
    if not any(adjust.values()):
        return None
    return st.review.adjusted_pose(pid, adjust["turn_deg"], (adjust["shift_x_mm"], adjust["shift_y_mm"]),
                                   max_side_px=int(st.settings["picture_px"]))


@bp.get("/api/review/picture/<int:pid>/<view>.png")
@needs_proposals
def picture(pid, view):
    st = station()
    if view not in VIEWS or not 0 <= pid < 2 ** 63:  # no proposal id beyond SQLite's integers
        abort(404)
    adjust = _adjustment(request.args)
    side = int(st.settings["picture_px"])
    px = request.args.get("px", side)
    try:   # a smaller picture (the candidate poses' strip): 64 px up to the pictures' own size
        px = int(px)
    except (TypeError, ValueError):
        abort(400, f"px must be a whole number of pixels, got {str(px)[:40]!r}")
    if not 64 <= px <= side:
        abort(400, f"px must be within 64-{side} (the review pictures' size), got {px}")
    try:
        pose = _adjusted(st, pid, adjust) if view.startswith("joined") else None   # in mm: the same at any size
        png = st.review.picture(pid, view, max_side_px=px, pose=pose)
    except LookupError as exc:
        return jsonify(error=str(exc)), 404
    return png, 200, {"Content-Type": "image/png", "Cache-Control": "private, max-age=60"}


@bp.get("/api/review/alternatives/<int:pid>")
@needs_proposals
def alternatives(pid):
    """The proposal's other candidate poses as adjustments of its pose (best first), for stepping;
    ``cluster``: the adjustment that fits B into a corner of A's confirmed cluster (or A into B's), where the
    reconstruction found one (``docking``: it is still looking); and ``proposed``: for a proposal that stands at
    its verdict's pose, the adjustment back to the matcher's proposed pose (else null)."""
    from .reconstruction import cluster_fit

    st = station()
    if not 0 <= pid < 2 ** 63:
        abort(404)
    side = int(st.settings["picture_px"])
    try:
        alternatives = st.review.alternatives(pid, max_side_px=side)
        prop = st.review.proposal(pid)
        fit, docking = cluster_fit(prop)
        cluster = proposed = None
        if fit is not None:
            cluster = {**st.review.adjustments(pid, [fit], max_side_px=side)[0],
                       "cluster": fit["cluster"], "faces": fit["faces"]}
        if prop["proposed_pose"] is not None and prop["proposed_pose"] != prop["pose"]:
            proposed = st.review.adjustments(pid, [prop["proposed_pose"]], max_side_px=side)[0]
    except LookupError as exc:
        return jsonify(error=str(exc)), 404
    return jsonify(proposal=pid, alternatives=alternatives, cluster=cluster, docking=docking, proposed=proposed)


@bp.post("/api/review/verdict")
@writes
@needs_proposals
def verdict():
    st = station()
    b = body()
    verdict = b.get("verdict")
    if verdict not in ("confirmed", "rejected"):
        return jsonify(error="verdict must be 'confirmed' or 'rejected' (skip sends nothing)"), 400
    prop = st.review.proposal(b.get("proposal"))
    if prop is None:
        return jsonify(error=f"no proposal {b.get('proposal')!r}"), 404
    by = who()
    if b.get("adjust") is not None and not isinstance(b.get("adjust"), dict):
        return jsonify(error="adjust must be an object of turn_deg, shift_x_mm, shift_y_mm"), 400
    adjust = _adjustment(b.get("adjust"))
    # the pose the conservator set (or saw) is the one the verdict keeps: a decided proposal's stands at its
    # latest verdict's pose (a confirmation's correction), so confirming it again without a new one keeps that
    try:
        pose = _adjusted(st, prop["id"], adjust) or prop.get("pose")
    except LookupError as exc:
        return jsonify(error=str(exc)), 409
    extra = {"pose": pose} if pose else {}
    msg = new_message("match.verified", fragment=prop["fragment_a"], other=prop["fragment_b"], verdict=verdict,
                      proposal=prop["id"], probability=prop["probability"], by=by,
                      model_version=prop.get("model_version"), **extra)
    delivered = submit_or_503(msg, "verdict")
    st.review.sent(prop["id"], verdict, pose, msg["time"])   # the proposal stands at it until the matcher records it
    entry = {"fragment_a": prop["fragment_a"], "fragment_b": prop["fragment_b"], "verdict": verdict, "by": by,
             "time": msg["time"], "uid": msg["uid"], "proposal": prop["id"], "delivered": delivered, "pose": pose}
    st.sent_verdicts.appendleft(entry)
    return jsonify(sent=entry)
