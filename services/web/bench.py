"""The bench page (``/bench``): the operator's front end to the scanner, and its JSON API.

This process owns the scanner: the capture runs in a background thread
(:class:`common.web.bench.BenchSession`, built by :func:`services.web.station.build_bench`) and
today's fragments with their pipeline state update live (long-poll on ``/api/bench?after=``).
"""

from __future__ import annotations

import collections
import time
from typing import Callable

from flask import Blueprint, abort, jsonify, render_template, request

from common.web.bench import BenchBusy
from common.web.catalogue import colour_only_stages
from common.web.pipeline import fragment_state, fragments_since, start_of_today

from .auth import body, writes
from .station import station

bp = Blueprint("bench", __name__)


@bp.get("/bench")
def page():
    return render_template("bench.html", page="bench")


@bp.get("/api/bench")
def state():
    st = station()
    after = request.args.get("after", type=int)
    if st.bench is None:
        out = {"phase": "none", "message": "No scanner is attached to this station.", "seq": 0, "history": []}
    elif after is not None:
        out = st.bench.wait_for_change(after, float(st.settings["long_poll_s"]))
    else:
        out = st.bench.state()
    return jsonify(bench=out, fragments=today_fragments(), time=time.time())


@bp.get("/api/bench/prescan.png")
def prescan_png():
    bench = station().bench
    png = bench.prescan_png() if bench is not None else None
    if not png:
        abort(404)
    return png, 200, {"Content-Type": "image/png"}


@bp.post("/api/bench/prescan")
@writes
def prescan():
    return _act(lambda bench, b: bench.prescan(b.get("fragment", "")))


@bp.post("/api/bench/empty-glass")
@writes
def empty_glass():
    return _act(lambda bench, b: bench.scan_empty_glass())


@bp.post("/api/bench/scan")
@writes
def scan():
    return _act(lambda bench, b: bench.start(b.get("fragment", "")))


@bp.post("/api/bench/proceed")
@writes
def proceed():
    return _act(lambda bench, b: bench.proceed(_step_index(b)))


def _step_index(b: dict) -> int:
    """The ``step`` a confirmation names; ValueError (answered 400) for anything but a whole number,
    so ``null`` or a list is the operator's page's mistake, not a server error."""
    try:
        return int(b.get("step", -1))
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"step must be the index of the step done, got {b.get('step')!r}") from None


@bp.post("/api/bench/cancel")
@writes
def cancel():
    return _act(lambda bench, b: bench.cancel())


def _act(fn: Callable):
    bench = station().bench
    if bench is None:
        return jsonify(error="No scanner is attached to this station."), 409
    try:
        return jsonify(bench=fn(bench, body()))
    except BenchBusy as exc:
        return jsonify(error=str(exc)), 409
    except ValueError as exc:
        return jsonify(error=str(exc)), 400


def today_fragments() -> list[dict]:
    """Fragments scanned today with their pipeline state, plus captures kept on this machine.

    A colour-only fragment (a ``--colour-only`` scan: its faces have no normals) has ``normals: n/a``, as in the
    catalogue: told from the catalogue's index of its faces (``has_normals``), not by opening them again; until
    the catalogue has indexed the face (or on a station without a catalogue) the stage shows as the tree says."""
    st = station()
    matched = st.review.matched_fragments() if st.review is not None else set()
    failed = failures_by_fragment(st.link)
    today = fragments_since(st.store_root, start_of_today())
    faces = st.catalogue.faces(fid for fid, _ in today) if st.catalogue is not None else {}
    rows = []
    for fid, t in today:
        row = fragment_state(st.store_root, fid, matched=matched, failed=failed.get(fid))
        row["stages"] = colour_only_stages(row["stages"], faces.get(fid, {}))
        row["scanned_at"] = t
        rows.append(row)
    if st.bench is not None:   # captures kept locally (lab unreachable) are not on storage yet
        listed = {r["fragment"] for r in rows}
        for rec in st.bench.state()["history"]:
            if rec["outcome"] == "kept" and rec["fragment"] not in listed:
                rows.insert(0, {"fragment": rec["fragment"], "stages": {"scanned": "kept"}, "errors": {},
                                "updated": rec["finished"], "scanned_at": rec["started"]})
                listed.add(rec["fragment"])
    return rows


def failures_by_fragment(link) -> dict[str, dict[str, str]]:
    """Parked jobs' errors by fragment and service, from the broker's (cached) status; {} if away."""
    if link is None:
        return {}
    try:
        parked = link.status(cached_s=5.0).get("parked", [])
    except Exception:
        return {}
    out: dict[str, dict[str, str]] = collections.defaultdict(dict)
    for job in parked:
        if job.get("fragment"):
            out[str(job["fragment"])][str(job.get("service"))] = str(job.get("error", ""))
    return out
