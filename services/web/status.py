"""The status page (``/status``): the broker's status and re-running parked jobs."""

from __future__ import annotations

from flask import Blueprint, jsonify, render_template

from .auth import body, writes
from .station import station

bp = Blueprint("status", __name__)


@bp.get("/status")
def page():
    return render_template("status.html", page="status")


@bp.get("/api/status")
def state():
    link = station().link
    if link is None:
        return jsonify(error="the broker is not configured on this station"), 503
    try:
        st = link.status()
    except Exception as exc:
        return jsonify(error=f"the broker cannot be reached: {exc}", reachable=False), 503
    st["reachable"] = True
    st["outbox"] = link.outbox_depth()
    return jsonify(st)


@bp.post("/api/status/rerun")
@writes
def rerun():
    link = station().link
    if link is None:
        return jsonify(error="the broker is not configured on this station"), 503
    job = body().get("job", "")
    if not isinstance(job, str):
        return jsonify(error=f"job must be a parked job's id (a string) or 'all', got {type(job).__name__}"), 400
    job = job.strip()
    if not job:
        return jsonify(error="name the parked job to re-run (or 'all')"), 400
    try:
        return jsonify(link.rerun(job))
    except Exception as exc:
        return jsonify(error=f"the broker cannot be reached: {exc}"), 503
