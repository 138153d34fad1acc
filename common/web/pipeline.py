"""Pipeline state of fragments, read from the storage tree (what the bench page lists).

Every stage writes its outputs under ``fragments/<id>/<stage>/`` (see ``docs/storage.md``), and
artifacts appear atomically (rename), so the tree itself is a restart-proof record of how far each
fragment got: no event can be missed by a page that was closed. A stage that failed its last
attempt shows as failed when the broker's parked jobs name the fragment.
"""

from __future__ import annotations

import datetime as _dt
import os
from pathlib import Path
from typing import Iterable, Mapping

#: stages shown for every fragment, in pipeline order, with the folders whose files mark them done
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("scanned", ("scans",)),
    ("normals", ("rgbn",)),
    ("features", ("features",)),
    ("matched", ("matches", "matcher")),
    ("rendered", ("renders", "render", "renderer")),
)

# the service whose failure blocks each stage
STAGE_SERVICE = {"normals": "solver", "features": "features", "matched": "matcher", "rendered": "renderer"}


def _artifacts(folder: Path) -> list[Path]:
    try:
        return [p for p in folder.iterdir() if p.suffix == ".h5" and not p.name.startswith(".")]
    except (FileNotFoundError, NotADirectoryError):
        return []


def fragment_state(root: str | os.PathLike, fragment_id: str, *, matched: Iterable[str] = (),
                   failed: Mapping[str, str] | None = None) -> dict:
    """How far one fragment has got through the pipeline.

    Parameters
    ----------
    root : path
        Storage root.
    fragment_id : str
    matched : iterable of str
        Fragments the matcher has taken in (e.g. ``ProposalStore.fragments()``), for matchers
        that keep their results in a database rather than in the tree.
    failed : mapping service -> error text, optional
        Parked failures of this fragment's jobs; they mark the stage failed even when some of
        its outputs exist (one face solved, the other not).

    Returns
    -------
    dict
        ``{"fragment", "stages": {stage: "done" | "waiting" | "failed"}, "errors": {stage: text},
        "updated": last artifact time (UNIX s) or None}``.
    """
    base = Path(root) / "fragments" / fragment_id
    matched = set(matched)
    failed = dict(failed or {})
    stages, errors, updated = {}, {}, None
    for stage, folders in STAGES:
        files = [f for d in folders for f in _artifacts(base / d)]
        done = bool(files) or (stage == "matched" and fragment_id in matched)
        if files:
            t = max(f.stat().st_mtime for f in files)
            updated = t if updated is None else max(updated, t)
        service = STAGE_SERVICE.get(stage)
        if service and service in failed:
            # a parked job outranks outputs: one face may be done while the other failed
            stages[stage] = "failed"
            errors[stage] = failed[service]
        elif done:
            stages[stage] = "done"
        else:
            stages[stage] = "waiting"
    return {"fragment": fragment_id, "stages": stages, "errors": errors, "updated": updated}


def fragments_since(root: str | os.PathLike, since: float) -> list[tuple[str, float]]:
    """Fragments whose scans were stored at or after ``since`` (UNIX s), newest first.

    Returns ``[(fragment_id, scan time), ...]``.
    """
    out = []
    frag_root = Path(root) / "fragments"
    try:
        entries = list(os.scandir(frag_root))
    except FileNotFoundError:
        return []
    for entry in entries:
        scans = Path(entry.path) / "scans"
        try:
            # one stat per fragment: a folder gains a file only by a rename into it, which updates
            # its mtime, so older folders cannot hold a scan stored since ``since``
            if scans.stat().st_mtime < since:
                continue
        except (FileNotFoundError, NotADirectoryError):
            continue
        files = _artifacts(scans)
        if not files:
            continue
        t = min(f.stat().st_mtime for f in files)
        if t >= since:
            out.append((entry.name, t))
    out.sort(key=lambda x: -x[1])
    return out


def start_of_today(now: float | None = None) -> float:
    """UNIX time of local midnight today (the bench page lists today's fragments)."""
    now_dt = _dt.datetime.fromtimestamp(_dt.datetime.now().timestamp() if now is None else now)
    return now_dt.replace(hour=0, minute=0, second=0, microsecond=0).timestamp()
