"""The archive's catalogue: one row per fragment, searchable and pageable at 10,000+ fragments.

The truth is elsewhere — artifacts on storage (faces, their importer metadata, how far the
pipeline got), the matcher's proposal store (joins) and the bus (metadata edits, as
``fragment.annotated`` events). Walking 10,000 fragment folders and opening their HDF5 files for
every page view would take minutes, so the catalogue keeps an **index table in SQLite**: rows
with indexed columns (state, colour family, join counts) and a lower-cased search text, so a page
of results with any filter is one indexed query (milliseconds; ``tests/bench/bench_web.py``). The
index is a cache, never the record: :meth:`Catalogue.rebuild` recreates it from storage (every
fragment folder, every face's metadata, every annotation file), and :meth:`Catalogue.apply`
keeps it current from the event feed. SQLite because it is in the standard library, is one file
that can be deleted and rebuilt, and answers ``WHERE … ORDER BY … LIMIT/OFFSET`` with indexes;
the proposal store already made the same choice (``docs/storage.md``).

Metadata edits: a person's edit is a ``fragment.annotated`` event (``fragment``, ``changes``
{field: new value}, ``by``, ``time``, ``uid``) submitted to the broker, which journals and
publishes it. The catalogue applies it from the feed: the fields change, the edit joins the
fragment's history, and the edit is written to storage as
``fragments/<id>/annotations/<time>-<uid>.json`` (atomic, immutable, named by its uid), so that a
rebuild restores the history and the current values even after the broker's feed has moved on.
Edits apply in ``(time, uid)`` order over the metadata the importer stored in the face's artifact.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import threading
from pathlib import Path
from typing import Callable, Iterable, Mapping

import numpy as np

from common.messages import ANNOTATION_FIELDS, MAX_ANNOTATION_CHARS
from common.store import ArtifactError, Store

log = logging.getLogger("tessera.web")

#: metadata fields a person edits (``tessera import images --manifest`` columns); the
#: ``fragment.annotated`` schema (:mod:`common.messages`, checked at the broker) declares them
FIELDS = ANNOTATION_FIELDS
#: longest value of a field, characters
MAX_FIELD_CHARS = MAX_ANNOTATION_CHARS
#: pipeline stages in order (:data:`common.web.pipeline.STAGES`)
STAGE_ORDER = ("scanned", "normals", "features", "matched", "rendered")
#: colour families a fragment can be filtered by (:func:`colour_family`)
COLOUR_FAMILIES = ("white", "grey", "black", "red", "orange", "yellow", "green", "blue", "purple")
#: longest side of the thumbnails, pixels
THUMB_PX = 128
#: event types that change a fragment's row (``input.rejected`` parks a job like ``stage.failed``)
FRAGMENT_EVENTS = ("fragment.ready", "rgbn.ready", "features.ready", "render.ready", "stage.failed",
                   "input.rejected", "fragment.annotated")
#: event types that change join counts
JOIN_EVENTS = ("match.proposed", "match.verified")
#: what the rows hold: an index whose rows another version made is rebuilt from storage at the next start
ROWS_VERSION = "3"   # 2: an imported fragment's stages say ``imported`` (not ``scanned: waiting``), and when / from what;
#                     3: a colour-only fragment's ``normals`` stage is ``n/a`` (was ``done``)
#: the status of a stage that does not apply to a fragment (the ``normals`` of a colour-only one), besides
#: ``done``, ``waiting`` and ``failed``: passed, like ``done``, by :func:`pipeline_state`
NOT_APPLICABLE = "n/a"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS fragments (
    id TEXT PRIMARY KEY,
    inventory TEXT NOT NULL DEFAULT '', find_spot TEXT NOT NULL DEFAULT '', context TEXT NOT NULL DEFAULT '',
    date TEXT NOT NULL DEFAULT '', notes TEXT NOT NULL DEFAULT '',
    imported TEXT NOT NULL DEFAULT '{}',      -- metadata as the importer stored it (JSON)
    extra TEXT NOT NULL DEFAULT '{}',         -- other manifest columns (JSON)
    state TEXT NOT NULL DEFAULT 'scanned', stages TEXT NOT NULL DEFAULT '{}', failed INTEGER NOT NULL DEFAULT 0,
    faces TEXT NOT NULL DEFAULT '{}',         -- {face: {rgbn, dpi, width, height, has_normals}}
    colour TEXT NOT NULL DEFAULT '',
    pending INTEGER NOT NULL DEFAULT 0, confirmed INTEGER NOT NULL DEFAULT 0,
    thumb BLOB, thumb_source TEXT NOT NULL DEFAULT '',
    search TEXT NOT NULL DEFAULT '',          -- lower-cased id + metadata, for substring search
    updated REAL NOT NULL DEFAULT 0);
CREATE INDEX IF NOT EXISTS fragments_state ON fragments (state, id);
CREATE INDEX IF NOT EXISTS fragments_colour ON fragments (colour, id);
CREATE INDEX IF NOT EXISTS fragments_confirmed ON fragments (confirmed, id);
CREATE TABLE IF NOT EXISTS edits (
    uid TEXT PRIMARY KEY, fragment TEXT NOT NULL, by TEXT NOT NULL, time REAL NOT NULL,
    changes TEXT NOT NULL, seq INTEGER);
CREATE INDEX IF NOT EXISTS edits_fragment ON edits (fragment, time);
"""


# --------------------------------------------------------------------------------------------
# the algorithms
# --------------------------------------------------------------------------------------------
def colour_family(rgba: np.ndarray) -> str:
    """The colour family most pixels of a fragment belong to.

    Parameters
    ----------
    rgba : (h, w, 4) uint8
        Display sRGB and coverage (a thumbnail, :func:`common.web.tiles.face_thumbnail`); pixels
        with alpha < 128 are off the fragment.

    Returns
    -------
    str
        One of :data:`COLOUR_FAMILIES`, or ``""`` when no pixel is on the fragment.

    Notes
    -----
    Each pixel is classed in HSV: value < 0.2 black; saturation < 0.2 white (value > 0.8) or
    grey; otherwise by hue: red < 15° or >= 330°, orange (ochres, browns) < 45°, yellow < 70°,
    green < 170°, blue < 260°, purple < 330°. The family is the most frequent class.

    Examples
    --------
    >>> px = np.zeros((2, 2, 4), np.uint8); px[..., 0] = 200; px[..., 3] = 255
    >>> colour_family(px)
    'red'
    """
    a = np.asarray(rgba)
    if a.ndim != 3 or a.shape[2] != 4 or a.dtype != np.uint8:
        raise ValueError(f"rgba must be (h, w, 4) uint8, got {a.shape} {a.dtype}")
    px = a[a[..., 3] >= 128][:, :3].astype(np.float32) / 255.0
    if not len(px):
        return ""
    mx, mn = px.max(axis=1), px.min(axis=1)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-6), 0.0)
    hue = _hue_deg(px, mx, mn)
    cls = np.select(
        [mx < 0.2, (sat < 0.2) & (mx > 0.8), sat < 0.2, (hue < 15) | (hue >= 330), hue < 45, hue < 70, hue < 170,
         hue < 260],
        [2, 0, 1, 3, 4, 5, 6, 7], default=8)
    return COLOUR_FAMILIES[int(np.bincount(cls, minlength=len(COLOUR_FAMILIES)).argmax())]


def _hue_deg(px: np.ndarray, mx: np.ndarray, mn: np.ndarray) -> np.ndarray:
    """HSV hue in degrees of (n, 3) RGB in [0, 1] (as :func:`colorsys.rgb_to_hsv`, vectorised)."""
    r, g, b = px.T
    d = np.maximum(mx - mn, 1e-6)
    h = np.where(mx == r, (g - b) / d % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4))
    return np.where(mx == mn, 0.0, h * 60.0)


def pipeline_state(stages: Mapping[str, str]) -> str:
    """One word for how far a fragment got: ``failed`` if a stage failed, else the last stage of
    :data:`STAGE_ORDER` reached without a gap (``scanned`` … ``rendered``), ``waiting`` if none.
    An imported fragment (stage ``imported`` in place of ``scanned``: :func:`imported_stages`) has no
    scans: its first stage is ``normals``. A stage that does not apply (:data:`NOT_APPLICABLE`: the
    ``normals`` of a colour-only fragment, :func:`colour_only_stages`) is passed as if done."""
    if any(v == "failed" for v in stages.values()):
        return "failed"
    state = "waiting"
    for stage in STAGE_ORDER:
        if stages.get(stage) not in ("done", NOT_APPLICABLE):
            if stage == "scanned" and (stages.get("imported") == "done" or stages.get("normals") == "done"):
                continue
            break
        state = stage
    return state


def imported_stages(stages: Mapping[str, str], has_faces: bool) -> dict[str, str]:
    """The stages of a fragment as they apply to it: one with faces and no scans was imported (``tessera
    import``), not scanned, so its first stage is ``imported: done`` in place of ``scanned: waiting``.

    >>> imported_stages({"scanned": "waiting", "normals": "done"}, True)
    {'imported': 'done', 'normals': 'done'}
    >>> imported_stages({"scanned": "done", "normals": "done"}, True)
    {'scanned': 'done', 'normals': 'done'}
    """
    if stages.get("scanned") == "done" or not has_faces:
        return dict(stages)
    return {"imported": "done", **{k: v for k, v in stages.items() if k != "scanned"}}


def colour_only_stages(stages: Mapping[str, str], faces: Mapping[str, Mapping]) -> dict[str, str]:
    """The stages of a fragment whose every face is colour-only (``has_normals`` false: an imported picture,
    a ``--colour-only`` scan): its ``normals`` stage is :data:`NOT_APPLICABLE`, not ``done`` (the face is
    stored, but it has no normals). A failed stage stays failed; a face that could not be read, or one
    with normals, leaves the stages as they are.

    >>> colour_only_stages({"imported": "done", "normals": "done"}, {"front": {"has_normals": False}})
    {'imported': 'done', 'normals': 'n/a'}
    >>> colour_only_stages({"scanned": "done", "normals": "done"},
    ...                    {"front": {"has_normals": True}, "back": {"has_normals": False}})
    {'scanned': 'done', 'normals': 'done'}
    """
    out = dict(stages)
    if faces and out.get("normals") == "done" and all(f.get("has_normals") is False for f in faces.values()):
        out["normals"] = NOT_APPLICABLE
    return out


def check_changes(changes) -> dict[str, str]:
    """The ``changes`` of a metadata edit, checked: a non-empty map of :data:`FIELDS` to strings
    of at most :data:`MAX_FIELD_CHARS` characters (``""`` clears a field). ValueError names the problem."""
    if not isinstance(changes, Mapping) or not changes:
        raise ValueError(f"changes must be a non-empty map of field to text (fields: {', '.join(FIELDS)})")
    out = {}
    for key, value in changes.items():
        if key not in FIELDS:
            raise ValueError(f"unknown field {key!r} (fields: {', '.join(FIELDS)})")
        if not isinstance(value, str):
            raise ValueError(f"field {key} must be text, got {type(value).__name__}")
        if len(value) > MAX_FIELD_CHARS:
            raise ValueError(f"field {key} is {len(value)} characters; at most {MAX_FIELD_CHARS}")
        out[key] = value.strip()
    return out


# --------------------------------------------------------------------------------------------
# the index
# --------------------------------------------------------------------------------------------
class Catalogue:
    """The catalogue's SQLite index (see the module docstring).

    Parameters
    ----------
    path : path
        The index file (created if missing; may be deleted at any time: :meth:`rebuild`).
    store : common.store.Store
        The storage root it indexes.
    proposals : path, optional
        The matcher's proposal store (``[services.matcher] db``) for join counts.
    """

    def __init__(self, path: str | Path, store: Store, *, proposals: str | Path | None = None):
        self.path = Path(path)
        self.store = store
        self.proposals = Path(proposals) if proposals else None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._local = threading.local()
        self._write = threading.Lock()
        self._joins_stale = False
        with self._db() as db:
            db.executescript(_SCHEMA)
            made_by = db.execute("SELECT value FROM meta WHERE key = 'rows'").fetchone()
            if made_by is None or made_by[0] != ROWS_VERSION:
                # rows of another version: forget the feed position, so the first round rebuilds them
                db.execute("DELETE FROM meta WHERE key IN ('stream', 'seq')")
                db.execute("INSERT OR REPLACE INTO meta VALUES ('rows', ?)", (ROWS_VERSION,))

    @contextlib.contextmanager
    def _db(self):
        db = getattr(self._local, "db", None)
        if db is None:   # one connection per thread: requests run on many threads
            db = sqlite3.connect(self.path, timeout=30.0, isolation_level=None)
            db.row_factory = sqlite3.Row
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")   # an index: losing the last write costs a rebuild, no data
            self._local.db = db
        yield db

    # -- feed position ---------------------------------------------------------------------
    def position(self) -> tuple[str, int]:
        """``(stream id, last sequence number applied)`` of the event feed ("", 0 before any)."""
        with self._db() as db:
            rows = dict(db.execute("SELECT key, value FROM meta WHERE key IN ('stream', 'seq')").fetchall())
        return rows.get("stream", ""), int(rows.get("seq", 0))

    def set_position(self, stream: str, seq: int) -> None:
        with self._write, self._db() as db:
            db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", [("stream", stream), ("seq", str(int(seq)))])

    # -- building --------------------------------------------------------------------------
    def fragment_ids(self) -> list[str]:
        """Every fragment folder on storage (sorted)."""
        root = self.store.root / "fragments"
        try:
            return sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith("."))
        except FileNotFoundError:
            return []

    def index_fragment(self, fid: str, *, failed: Mapping[str, str] | None = None,
                       matched: Iterable[str] = ()) -> dict:
        """Read one fragment from storage (faces, importer metadata, annotations, pipeline state,
        thumbnail and colour family when its front face changed) and write its row."""
        from common.imports.export import latest_faces
        from common.web.pipeline import fragment_state
        from common.web.tiles import encode_png, face_thumbnail

        faces, imported = {}, {}
        for face, rel in latest_faces(self.store, fid).items():
            info = _face_info(self.store, rel)
            meta = info.pop("metadata")
            imported = imported or meta   # the first face that has the importer's metadata
            faces[face] = info
        st = fragment_state(self.store.root, fid, matched=matched, failed=failed)
        st["stages"] = colour_only_stages(imported_stages(st["stages"], bool(faces)), faces)
        edits = self._annotations_on_storage(fid)
        values = {k: str(imported.get(k, "") or "") for k in FIELDS}
        for e in edits:
            values.update(e["changes"])
        extra = {k: v for k, v in imported.items() if k not in FIELDS}
        with self._db() as db:
            old = db.execute("SELECT thumb, thumb_source, colour, pending, confirmed FROM fragments WHERE id = ?",
                             (fid,)).fetchone()
        thumb_face = "front" if "front" in faces else next(iter(faces), None)
        source = faces[thumb_face]["rgbn"] if thumb_face else ""
        if old is not None and old["thumb_source"] == source:
            thumb, colour = old["thumb"], old["colour"]
        elif source:
            try:
                rgba = face_thumbnail(self.store, source, THUMB_PX)
                thumb, colour = encode_png(rgba), colour_family(rgba)
            except (ArtifactError, OSError, ValueError) as exc:   # listed without a picture, never dropped
                log.warning("catalogue: no thumbnail of %s: %s", source, exc)
                thumb, colour = None, ""
        else:
            thumb, colour = None, ""
        row = {"id": fid, **values, "imported": json.dumps(imported, sort_keys=True, default=str),
               "extra": json.dumps(extra, sort_keys=True, default=str), "state": pipeline_state(st["stages"]),
               "stages": json.dumps(st["stages"]), "failed": int("failed" in st["stages"].values()),
               "faces": json.dumps(faces, sort_keys=True), "colour": colour,
               "pending": old["pending"] if old is not None else 0,
               "confirmed": old["confirmed"] if old is not None else 0,
               "thumb": thumb, "thumb_source": source, "search": _search_text(fid, values, extra),
               "updated": float(st["updated"] or 0.0)}
        with self._write, self._db() as db:
            db.execute("BEGIN")
            db.execute(f"INSERT OR REPLACE INTO fragments ({', '.join(row)}) VALUES ({', '.join('?' * len(row))})",
                       list(row.values()))
            db.executemany("INSERT OR IGNORE INTO edits (uid, fragment, by, time, changes) VALUES (?, ?, ?, ?, ?)",
                           [(e["uid"], fid, e["by"], e["time"], json.dumps(e["changes"], sort_keys=True))
                            for e in edits])
            db.execute("COMMIT")
        return row

    def rebuild(self, *, failed: Mapping[str, Mapping[str, str]] | None = None,
                progress: Callable[[int, int, str], None] | None = None) -> int:
        """Recreate every row from storage and the proposal store; return the number of fragments.

        Rows of fragments no longer on storage are dropped; thumbnails of unchanged faces are kept.
        """
        ids = self.fragment_ids()
        matched = self._matched()
        for i, fid in enumerate(ids):
            self.index_fragment(fid, failed=(failed or {}).get(fid), matched=matched)
            if progress is not None:
                progress(i + 1, len(ids), fid)
        with self._write, self._db() as db:
            db.execute("BEGIN")
            db.execute("CREATE TEMP TABLE IF NOT EXISTS keep (id TEXT PRIMARY KEY)")
            db.execute("DELETE FROM keep")
            db.executemany("INSERT INTO keep VALUES (?)", [(f,) for f in ids])
            db.execute("DELETE FROM fragments WHERE id NOT IN (SELECT id FROM keep)")
            db.execute("COMMIT")
        self.refresh_joins()
        return len(ids)

    def refresh_joins(self) -> None:
        """Pending and confirmed join counts of every fragment, from the proposal store."""
        counts: dict[str, tuple[int, int]] = {}
        if self.proposals is not None and self.proposals.is_file():
            src = sqlite3.connect(f"file:{self.proposals}?mode=ro", uri=True, timeout=30.0)
            try:
                for fid, pending, confirmed in src.execute(
                        "SELECT f, SUM(status = 'pending'), SUM(status = 'confirmed') FROM ("
                        " SELECT fragment_a AS f, status FROM proposals UNION ALL"
                        " SELECT fragment_b AS f, status FROM proposals) GROUP BY f"):
                    counts[fid] = (int(pending or 0), int(confirmed or 0))
            except sqlite3.OperationalError:   # no proposals table yet
                pass
            finally:
                src.close()
        with self._write, self._db() as db:
            db.execute("BEGIN")
            db.execute("UPDATE fragments SET pending = 0, confirmed = 0 WHERE pending != 0 OR confirmed != 0")
            db.executemany("UPDATE fragments SET pending = ?, confirmed = ? WHERE id = ?",
                           [(p, c, f) for f, (p, c) in counts.items()])
            db.execute("COMMIT")
        self._mark_matched()

    def _mark_matched(self) -> None:
        """Set the ``matched`` stage of fragments the matcher has taken in since their row was written.

        A fragment's row is written on its artifact events; when the matcher records it only after the
        last of them (it was busy, e.g. training its first model), only match events follow, and the row
        would keep ``matched: waiting`` (state ``features``) until a rebuild."""
        matched = self._matched()
        if not matched:
            return
        with self._db() as db:
            rows = db.execute("SELECT id, stages FROM fragments WHERE state != 'failed'").fetchall()
        updates = []
        for r in rows:
            stages = json.loads(r["stages"])
            if r["id"] in matched and stages.get("matched") == "waiting":
                stages["matched"] = "done"
                updates.append((json.dumps(stages), pipeline_state(stages), r["id"]))
        if updates:
            with self._write, self._db() as db:
                db.execute("BEGIN")
                db.executemany("UPDATE fragments SET stages = ?, state = ? WHERE id = ?", updates)
                db.execute("COMMIT")

    def _matched(self) -> set[str]:
        if self.proposals is None or not self.proposals.is_file():
            return set()
        with contextlib.closing(sqlite3.connect(f"file:{self.proposals}?mode=ro", uri=True, timeout=30.0)) as src:
            try:
                return {r[0] for r in src.execute("SELECT fragment FROM fragments")}
            except sqlite3.OperationalError:
                return set()

    # -- the feed --------------------------------------------------------------------------
    def apply(self, event: Mapping, seq: int | None = None, *,
              failed: Mapping[str, Mapping[str, str]] | None = None) -> str:
        """Apply one feed event; return what it did (``annotated``, ``reindexed``, ``joins``, ``ignored``).

        ``fragment.annotated`` is written to storage (:meth:`record_annotation`) and its fragment
        re-indexed; an event announcing a fragment's artifact or failure re-indexes that fragment;
        match events mark the join counts for recounting at the next :meth:`flush`.
        """
        kind, fid = event.get("type"), event.get("fragment")
        if kind in FRAGMENT_EVENTS and fid:
            if not (self.store.root / "fragments" / str(fid)).is_dir():
                return "ignored"   # nothing of it on storage (yet): a later event or a rebuild brings it
            if kind == "fragment.annotated":
                self.record_annotation(event, seq)
            self.index_fragment(str(fid), failed=(failed or {}).get(str(fid)), matched=self._matched())
            return "annotated" if kind == "fragment.annotated" else "reindexed"
        if kind in JOIN_EVENTS:
            self._joins_stale = True   # counted once per batch of events (:meth:`flush`): a re-rank sends thousands
            return "joins"
        return "ignored"

    def flush(self) -> None:
        """Recount the joins if a match event came since the last count (call after a batch of events)."""
        if self._joins_stale:
            self._joins_stale = False
            self.refresh_joins()

    def record_annotation(self, event: Mapping, seq: int | None = None) -> str:
        """Write a ``fragment.annotated`` event to ``fragments/<id>/annotations/`` (once; atomic)."""
        from common.messages import FRAGMENT_PATTERN, UID_PATTERN
        from common.store import write_file

        fid, uid = str(event["fragment"]), str(event["uid"])
        if not FRAGMENT_PATTERN.match(fid) or not UID_PATTERN.match(uid):
            raise ValueError(f"annotation of {fid!r} with uid {uid!r}: not a fragment id and message uid")
        record = {"uid": uid, "fragment": fid, "by": str(event.get("by", "")), "time": float(event["time"]),
                  "changes": check_changes(event.get("changes")), "seq": seq}
        rel = f"fragments/{fid}/annotations/{record['time']:017.6f}-{uid}.json"
        path = self.store.path(rel)
        if not path.is_file():
            write_file(path, (json.dumps(record, sort_keys=True, ensure_ascii=False) + "\n").encode())
        return rel

    def _annotations_on_storage(self, fid: str) -> list[dict]:
        folder = self.store.root / "fragments" / fid / "annotations"
        out = []
        for p in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            if p.name.startswith("."):
                continue
            with contextlib.suppress(OSError, ValueError, KeyError):
                rec = json.loads(p.read_text(encoding="utf-8"))
                out.append({"uid": rec["uid"], "by": rec.get("by", ""), "time": float(rec["time"]),
                            "changes": check_changes(rec["changes"])})
        out.sort(key=lambda e: (e["time"], e["uid"]))
        return out

    # -- reading ---------------------------------------------------------------------------
    def query(self, *, text: str = "", state: str = "", colour: str = "", joins: str = "",
              page: int = 1, per_page: int = 50) -> dict:
        """A page of fragments (sorted by id) and the number matching.

        Parameters
        ----------
        text : str
            Substring of the id or any metadata value (case-insensitive).
        state : str
            A :func:`pipeline_state` word (``failed``, ``rendered``, …).
        colour : str
            One of :data:`COLOUR_FAMILIES`.
        joins : {"", "confirmed", "pending", "none"}
            Has confirmed joins / has pending proposals / has neither.
        page, per_page : int
            1-based page; 1-500 rows a page.
        """
        where, args = [], []
        if text.strip():
            where.append("search LIKE ? ESCAPE '\\'")
            esc = text.strip().lower().replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
            args.append(f"%{esc}%")
        if state:
            if state not in ("waiting", "failed") + STAGE_ORDER:
                raise ValueError(f"state must be one of {', '.join(('waiting', 'failed') + STAGE_ORDER)}, got {state!r}")
            where.append("state = ?")
            args.append(state)
        if colour:
            if colour not in COLOUR_FAMILIES:
                raise ValueError(f"colour must be one of {', '.join(COLOUR_FAMILIES)}, got {colour!r}")
            where.append("colour = ?")
            args.append(colour)
        if joins:
            cond = {"confirmed": "confirmed > 0", "pending": "pending > 0", "none": "confirmed = 0 AND pending = 0"}
            if joins not in cond:
                raise ValueError(f"joins must be one of {', '.join(cond)}, got {joins!r}")
            where.append(cond[joins])
        page, per_page = int(page), int(per_page)
        if page < 1 or not 1 <= per_page <= 500:
            raise ValueError(f"page must be >= 1 and per_page 1-500, got {page}, {per_page}")
        sql_where = f"WHERE {' AND '.join(where)}" if where else ""
        with self._db() as db:
            total = db.execute(f"SELECT COUNT(*) FROM fragments {sql_where}", args).fetchone()[0]
            offset = (page - 1) * per_page
            # a page past the last is empty; not asked of SQLite, whose OFFSET is a 64-bit integer
            rows = [] if offset >= total else db.execute(
                f"SELECT {_COLUMNS} FROM fragments {sql_where} ORDER BY id LIMIT ? OFFSET ?",
                args + [per_page, offset]).fetchall()
        return {"total": int(total), "page": page, "per_page": per_page, "fragments": [_row(r) for r in rows]}

    def get(self, fid: str) -> dict | None:
        """One fragment's row with its edit history (newest first), or None."""
        with self._db() as db:
            r = db.execute(f"SELECT {_COLUMNS} FROM fragments WHERE id = ?", (fid,)).fetchone()
            if r is None:
                return None
            edits = db.execute("SELECT uid, by, time, changes, seq FROM edits WHERE fragment = ? "
                               "ORDER BY time DESC, uid DESC", (fid,)).fetchall()
        out = _row(r)
        out["history"] = [{"uid": e["uid"], "by": e["by"], "time": e["time"], "changes": json.loads(e["changes"]),
                           "seq": e["seq"]} for e in edits]
        return out

    def faces(self, fids: Iterable[str]) -> dict[str, dict]:
        """The indexed faces (``{face: {rgbn, dpi, width, height, has_normals}}``) of each of ``fids`` the index
        holds: what the bench page reads to tell a colour-only fragment (:func:`colour_only_stages`) without
        opening its faces again."""
        fids = list(dict.fromkeys(fids))
        out = {}
        with self._db() as db:
            for i in range(0, len(fids), 500):   # SQLite's limit on the ? of one statement
                chunk = fids[i:i + 500]
                for r in db.execute(f"SELECT id, faces FROM fragments WHERE id IN ({', '.join('?' * len(chunk))})",
                                    chunk):
                    out[r["id"]] = json.loads(r["faces"])
        return out

    def thumbnail(self, fid: str) -> bytes | None:
        with self._db() as db:
            r = db.execute("SELECT thumb FROM fragments WHERE id = ?", (fid,)).fetchone()
        return bytes(r[0]) if r is not None and r[0] is not None else None

    def counts(self) -> dict:
        """Number of fragments by state and by colour family, and in all."""
        with self._db() as db:
            states = dict(db.execute("SELECT state, COUNT(*) FROM fragments GROUP BY state").fetchall())
            colours = dict(db.execute("SELECT colour, COUNT(*) FROM fragments GROUP BY colour").fetchall())
        return {"total": sum(states.values()), "states": states, "colours": colours}

    def close(self) -> None:
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None


_COLUMNS = ("id, inventory, find_spot, context, date, notes, extra, state, stages, failed, faces, colour, pending, "
            "confirmed, thumb IS NOT NULL AS has_thumb, updated")


def _row(r: sqlite3.Row) -> dict:
    out = {k: r[k] for k in ("id", "inventory", "find_spot", "context", "date", "notes", "state", "colour",
                             "pending", "confirmed", "updated")}
    out.update(extra=json.loads(r["extra"]), stages=json.loads(r["stages"]), failed=bool(r["failed"]),
               faces=json.loads(r["faces"]), has_thumb=bool(r["has_thumb"]))
    out["imported"] = _imported(out["stages"], out["faces"])
    return out


def _imported(stages: Mapping, faces: Mapping) -> dict | None:
    """How an imported fragment came (``{"time", "by", "file", "face"}`` of its front face, else its first:
    the artifact's creation time, the importer, the source file's name; ``""`` where the face does not say),
    or None for a scanned one."""
    if stages.get("imported") != "done" or not faces:
        return None
    face = "front" if "front" in faces else next(iter(faces))
    how = faces[face].get("imported") or {}
    return {"face": face, "time": faces[face].get("created", ""), "by": how.get("by", ""), "file": how.get("file", "")}


def _search_text(fid: str, values: Mapping[str, str], extra: Mapping) -> str:
    parts = [fid] + [str(v) for v in values.values() if v] + [str(v) for v in extra.values() if v]
    return "\n".join(parts).lower()


def _import_record(attrs) -> dict:
    """By what and from which file a face was imported, from its artifact's attributes: ``by`` (the provenance's
    ``importer``, or the ``source`` every importer sets: ``tessera import images``, ``DAFNE``, …) and ``file``
    (the source file's or folder's name); ``""`` where they do not say (``by`` is ``""`` for a solved scan)."""
    def text(v):
        return v.decode() if isinstance(v, bytes) else str(v)

    try:
        prov = json.loads(text(attrs.get("provenance", "{}")))
    except ValueError:
        prov = {}
    prov = prov if isinstance(prov, dict) else {}
    files = prov.get("source_file") or prov.get("source_files") or prov.get("capture") or ""
    files = files[0] if isinstance(files, list) and files else files
    return {"by": str(prov.get("importer") or text(attrs.get("source", ""))), "file": Path(str(files)).name if files else ""}


def _face_info(store: Store, rel: str) -> dict:
    """dpi, size, normals and importer metadata of a face, from its attributes (no pixel read).

    Opened with its schema and the highest version this reader understands: a face it cannot read (not
    HDF5, not an RGBN image, written by a newer Tessera) is listed without those details, and the log says why."""
    from common.rgbn.image import SCHEMA as RGBN, SCHEMA_VERSION as RGBN_VERSION

    info = {"rgbn": rel, "metadata": {}}
    try:
        with store.open(rel, schema=RGBN, version=RGBN_VERSION) as f, \
                contextlib.suppress(OSError, KeyError, ValueError):
            h, w = f["mask"].shape
            info.update(dpi=float(f.attrs["dpi"]), width=int(w), height=int(h), has_normals="normals" in f)
            created = f.attrs.get("created", "")
            info["created"] = created.decode() if isinstance(created, bytes) else str(created)
            how = _import_record(f.attrs)
            if how["by"]:
                info["imported"] = how
            meta = f.attrs.get("metadata", "")
            if isinstance(meta, bytes):
                meta = meta.decode()
            if meta:
                parsed = json.loads(meta)
                if isinstance(parsed, dict):
                    info["metadata"] = parsed
    except (ArtifactError, OSError) as exc:   # listed without those details, never dropped
        log.warning("catalogue: face %s listed without its size, dpi and metadata: %s", rel, exc)
    return info

