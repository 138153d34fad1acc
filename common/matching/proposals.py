"""Durable, queryable store of join proposals and verdicts (thesis §5.2, §5.8).

Why SQLite
----------
Proposals are small rows that change (probabilities are re-ranked after every model update,
statuses change when a conservator decides), and people ask indexed questions of them: "the ranked
list for fragment F", "all pending proposals, most probable first", "every verdict in order". HDF5
artifacts are immutable by design, so they do not fit; a database server would be one more
service to run. SQLite gives transactions (a crash mid-update loses nothing committed), indexes,
and a single file that the standard library reads — any lab can open it with ``sqlite3``.

Where it lives
--------------
By default ``<storage root>/matches/proposals.sqlite`` (config ``matcher.db``). SQLite relies on
POSIX byte-range locks, which many NFS/SMB mounts implement badly; on a station whose storage root
is a network mount, either put the database on the **matcher host's local disk** (``matcher.db =
"/var/lib/tessera/proposals.sqlite"``) and run the matcher workers that write it, and the pages that read it, on
that host, or keep it on the share with ``journal_mode="DELETE"`` (``configs/lab.toml``: its review page runs on
the bench PC). The journal mode is WAL on local disks (readers never block the writer); on a network file system
WAL cannot work (it needs shared memory).

Dockings
--------
The matcher's stage 3 docks a pair once (~0.05–0.3 s CPU at real sizes) and reuses the result in every
later ranking of either fragment. The ``dockings`` table keeps one row per pair (:class:`StoredDocking`),
valid for the digests of the two fragments' docking inputs and the docking's version, so every matcher
worker that opens this store — a second one, or one restarted — reads the pairs another docked instead
of docking them again. They live here rather than as HDF5 artifacts because every matcher worker
already reaches this store (the fragments, proposals and the current model are in it), and a pair's
docking is a row of ~20 numbers read by key in microseconds: tens of thousands of tiny immutable files
would cost a file open per lookup, more on a network share.
"""

from __future__ import annotations

import json
import math
import os
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path

STATUSES = ("pending", "confirmed", "rejected")
#: the order of a fragment's proposals and of the review queue: mutual proximity (both fragments'
#: rankings, comparable across queries), then the probability (one query's), pairs without a mutual
#: proximity (stored before it existed) last
ORDER = "mutual IS NULL, mutual DESC, probability DESC, id"


def order_key(mutual: float | None, probability: float, pid: int | None) -> tuple:
    """Sort key of :data:`ORDER` for proposals outside the database (best first)."""
    return (mutual is None, -(mutual or 0.0), -probability, pid if pid is not None else 0)

VERDICTS = ("confirmed", "rejected")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS fragments (
    fragment TEXT NOT NULL, face TEXT NOT NULL, artifact TEXT NOT NULL, sha256 TEXT NOT NULL,
    bytes INTEGER NOT NULL, added REAL NOT NULL, PRIMARY KEY (fragment, face));
CREATE TABLE IF NOT EXISTS proposals (
    id INTEGER PRIMARY KEY,
    fragment_a TEXT NOT NULL, fragment_b TEXT NOT NULL,
    patch_a INTEGER, patch_b INTEGER,
    probability REAL NOT NULL,
    angle_deg REAL, tx_mm REAL, ty_mm REAL,
    alignment TEXT,
    evidence TEXT,
    model_version TEXT NOT NULL,
    status TEXT NOT NULL DEFAULT 'pending',
    created REAL NOT NULL, updated REAL NOT NULL,
    mutual REAL,
    UNIQUE (fragment_a, fragment_b));
CREATE INDEX IF NOT EXISTS proposals_a ON proposals (fragment_a, probability DESC);
CREATE INDEX IF NOT EXISTS proposals_b ON proposals (fragment_b, probability DESC);
CREATE INDEX IF NOT EXISTS proposals_status ON proposals (status, probability DESC);
CREATE TABLE IF NOT EXISTS verdicts (
    id INTEGER PRIMARY KEY,
    fragment_a TEXT NOT NULL, fragment_b TEXT NOT NULL,
    verdict TEXT NOT NULL, by TEXT, note TEXT,
    proposal_id INTEGER, model_version TEXT, message_uid TEXT UNIQUE,
    time REAL NOT NULL);
CREATE INDEX IF NOT EXISTS verdicts_pair ON verdicts (fragment_a, fragment_b, time);
CREATE TABLE IF NOT EXISTS models (
    version TEXT PRIMARY KEY, artifact TEXT NOT NULL, sha256 TEXT NOT NULL, bytes INTEGER NOT NULL,
    created REAL NOT NULL, n_train INTEGER, note TEXT);
CREATE TABLE IF NOT EXISTS dockings (
    fragment_a TEXT NOT NULL, fragment_b TEXT NOT NULL,
    inputs_a TEXT NOT NULL, inputs_b TEXT NOT NULL, docking_version TEXT NOT NULL,
    angle_deg REAL, tx_mm REAL, ty_mm REAL, score REAL, contact_mm REAL, overlap_mm2 REAL,
    paint INTEGER NOT NULL, paint_mm REAL, pose TEXT, alternatives TEXT,
    created REAL NOT NULL,
    PRIMARY KEY (fragment_a, fragment_b));
CREATE TABLE IF NOT EXISTS dock_hubness (
    fragment TEXT PRIMARY KEY, inputs TEXT NOT NULL, docking_version TEXT NOT NULL,
    contact_mm REAL NOT NULL, model_version TEXT, created REAL NOT NULL);
"""

#: the numbers of one docked pose in the ``dockings`` table's columns and JSON arrays, in this order
#: (common.matching.docking.Docking: B's pose in A's frame, degrees and mm; its score, contact mm, overlap mm²)
DOCKING_FIELDS = ("angle_deg", "tx_mm", "ty_mm", "score", "contact_mm", "overlap_mm2")


@dataclass
class Proposal:
    """One proposed join: fragment B relative to fragment A (``fragment_a < fragment_b``).

    ``angle_deg, tx_mm, ty_mm`` map B's fragment frame (mm) into A's; ``evidence`` holds the
    correspondence vectors of the best patch pairs (what the classifier saw, so a verdict can be
    learnt from without reloading features); ``alignment`` the per-match check's scores.
    """

    fragment_a: str
    fragment_b: str
    probability: float
    model_version: str
    patch_a: int | None = None
    patch_b: int | None = None
    angle_deg: float | None = None
    tx_mm: float | None = None
    ty_mm: float | None = None
    alignment: dict | None = None
    evidence: dict | None = None
    status: str = "pending"
    id: int | None = None
    created: float = 0.0
    updated: float = 0.0
    #: mutual proximity of the pair in both fragments' rankings (common.matching.mutual), in [0, 1);
    #: what a fragment's proposals and the review queue are ordered by; None before it is known
    mutual: float | None = None

    def other(self, fragment: str) -> str:
        return self.fragment_b if fragment == self.fragment_a else self.fragment_a

    def to_event_fields(self) -> dict:
        """Fields of a ``match.proposed`` message (without the evidence vectors)."""
        d = {"fragment": self.fragment_a, "other": self.fragment_b, "probability": float(self.probability),
             "model_version": self.model_version, "proposal": self.id, "status": self.status,
             "patches": [self.patch_a, self.patch_b]}
        if self.mutual is not None:
            d["mutual"] = float(self.mutual)
        if self.angle_deg is not None:
            d["pose"] = {"angle_deg": self.angle_deg, "tx_mm": self.tx_mm, "ty_mm": self.ty_mm,
                         "frame": "other in fragment: p_fragment = R(angle) p_other + t, mm, x right, y down"}
        if self.alignment:
            d["alignment"] = self.alignment
        return d


@dataclass
class Verdict:
    fragment_a: str
    fragment_b: str
    verdict: str
    time: float
    by: str | None = None
    note: str | None = None
    proposal_id: int | None = None
    model_version: str | None = None
    id: int | None = None
    #: the proposal's pose when the verdict was given (B in A's frame: angle_deg, tx_mm, ty_mm), or None
    pose: dict | None = None


@dataclass
class StoredDocking:
    """One fragment pair's docking as the matcher keeps it (:class:`common.matching.index.MatchIndex`): what
    the station's stage 3 found for ``fragment_b`` turned against ``fragment_a`` (``fragment_a < fragment_b``).

    Valid only for the inputs it was made from: ``inputs_a``, ``inputs_b`` are digests of the two fragments'
    docking inputs (their outline and boundary profile, :func:`common.matching.index.docking_inputs`) and
    ``docking_version`` the version of the docking that made it (:func:`common.matching.index.docking_version`).
    Every pose is a tuple in :data:`DOCKING_FIELDS` order, B in A's frame (``p_a = R(angle) p_b + t``, mm).
    """

    fragment_a: str
    fragment_b: str
    inputs_a: str
    inputs_b: str
    docking_version: str
    #: the docking's best pose (its geometric evidence: the contact)
    best: tuple
    #: docked with paint: then ``paint_mm`` (paint continuing across the crack, best over the candidate
    #: poses; NaN where none), ``pose`` (the proposed pose, by contact and paint) and ``alternatives``
    #: (the next-best distinct poses) are set; without paint they are NaN, None and empty
    paint: bool = False
    paint_mm: float = float("nan")
    pose: tuple | None = None
    alternatives: list = field(default_factory=list)
    created: float = 0.0


def ordered_pair(a: str, b: str) -> tuple[str, str]:
    """A fragment pair in its stored order (lexicographic); raises ValueError for a == b."""
    a, b = str(a), str(b)
    if a == b:
        raise ValueError(f"a fragment cannot join itself ({a!r})")
    return (a, b) if a < b else (b, a)


def proposals_path(root: str | os.PathLike, db: str | os.PathLike | None = None) -> Path:
    """Where a station's proposal database is: ``db`` (the ``[services.matcher] db`` setting) when set, else
    ``<storage root>/matches/proposals.sqlite`` (the module notes say when to set it)."""
    return Path(db) if db else Path(root) / "matches" / "proposals.sqlite"


class ProposalStore:
    """SQLite store of fragments seen, proposals, verdicts and model versions.

    Parameters
    ----------
    path : path
        Database file (created with its directory if absent). See the module notes on NFS.
    journal_mode : str
        ``"WAL"`` (default, local disk) or ``"DELETE"`` (network file systems).
    """

    def __init__(self, path: str | os.PathLike, *, journal_mode: str = "WAL", timeout_s: float = 30.0):
        if journal_mode.upper() not in ("WAL", "DELETE", "TRUNCATE"):
            raise ValueError(f"journal_mode must be WAL, DELETE or TRUNCATE, got {journal_mode!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(self.path), timeout=timeout_s, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._db.execute(f"PRAGMA journal_mode={journal_mode.upper()}")
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.executescript(_SCHEMA)  # idempotent; executescript manages its own transaction
        # databases made before verdicts kept the pose: add the column (NULL for old verdicts)
        if "pose" not in {r["name"] for r in self._db.execute("PRAGMA table_info(verdicts)")}:
            self._db.execute("ALTER TABLE verdicts ADD COLUMN pose TEXT")
        # databases made before mutual proximity: add the column (NULL until the pair is ranked again)
        if "mutual" not in {r["name"] for r in self._db.execute("PRAGMA table_info(proposals)")}:
            self._db.execute("ALTER TABLE proposals ADD COLUMN mutual REAL")
        self._db.execute("CREATE INDEX IF NOT EXISTS proposals_status_mutual ON proposals (status, mutual DESC)")

    def close(self) -> None:
        self._db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- transactions --------------------------------------------------------------------
    class _Tx:
        def __init__(self, db):
            self.db = db

        def __enter__(self):
            self.db.execute("BEGIN IMMEDIATE")

        def __exit__(self, kind, *_):
            self.db.execute("COMMIT" if kind is None else "ROLLBACK")

    def _tx(self):
        return self._Tx(self._db)

    # -- meta ----------------------------------------------------------------------------
    def get_meta(self, key: str, default: str | None = None) -> str | None:
        row = self._db.execute("SELECT value FROM meta WHERE key=?", (key,)).fetchone()
        return row[0] if row else default

    def set_meta(self, key: str, value: str) -> None:
        with self._tx():
            self._db.execute("INSERT INTO meta(key, value) VALUES(?, ?) ON CONFLICT(key) DO UPDATE SET value=excluded.value",
                             (key, str(value)))

    # -- fragments -----------------------------------------------------------------------
    def add_fragment(self, fragment: str, face: str, artifact: dict) -> bool:
        """Record a fragment face's feature artifact; returns False if that exact artifact was known."""
        with self._tx():
            row = self._db.execute("SELECT sha256 FROM fragments WHERE fragment=? AND face=?", (fragment, face)).fetchone()
            if row and row[0] == artifact["sha256"]:
                return False
            self._db.execute("INSERT OR REPLACE INTO fragments VALUES(?, ?, ?, ?, ?, ?)",
                             (fragment, face, artifact["path"], artifact["sha256"], int(artifact["bytes"]), time.time()))
        return True

    def fragments(self, face: str | None = None) -> list[dict]:
        q = "SELECT * FROM fragments" + (" WHERE face=?" if face else "") + " ORDER BY added, fragment"
        rows = self._db.execute(q, (face,) if face else ()).fetchall()
        return [{"fragment": r["fragment"], "face": r["face"],
                 "artifact": {"path": r["artifact"], "sha256": r["sha256"], "bytes": r["bytes"]}} for r in rows]

    # -- proposals -----------------------------------------------------------------------
    def upsert(self, proposals: list[Proposal]) -> list[Proposal]:
        """Insert or update proposals (one row per fragment pair); a decided pair keeps its status.

        Returns the stored proposals with their ids.
        """
        now = time.time()
        out = []
        with self._tx():
            for p in proposals:
                a, b = ordered_pair(p.fragment_a, p.fragment_b)
                if (a, b) != (p.fragment_a, p.fragment_b):
                    raise ValueError("proposal fragments must be in stored order: use ordered_pair()")
                self._db.execute(
                    """INSERT INTO proposals (fragment_a, fragment_b, patch_a, patch_b, probability, angle_deg, tx_mm,
                       ty_mm, alignment, evidence, model_version, status, created, updated, mutual)
                       VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, 'pending', ?, ?, ?)
                       ON CONFLICT(fragment_a, fragment_b) DO UPDATE SET patch_a=excluded.patch_a,
                       patch_b=excluded.patch_b, probability=excluded.probability,
                       angle_deg=COALESCE(excluded.angle_deg, angle_deg), tx_mm=COALESCE(excluded.tx_mm, tx_mm),
                       ty_mm=COALESCE(excluded.ty_mm, ty_mm), alignment=COALESCE(excluded.alignment, alignment),
                       evidence=excluded.evidence, model_version=excluded.model_version, updated=excluded.updated,
                       mutual=COALESCE(excluded.mutual, mutual)""",
                    (a, b, p.patch_a, p.patch_b, float(p.probability), p.angle_deg, p.tx_mm, p.ty_mm,
                     json.dumps(p.alignment) if p.alignment else None,
                     json.dumps(p.evidence) if p.evidence else None, p.model_version, now, now,
                     None if p.mutual is None else float(p.mutual)))
                out.append(self.get(a, b))
        return out

    def get(self, a: str, b: str) -> Proposal | None:
        a, b = ordered_pair(a, b)
        row = self._db.execute("SELECT * FROM proposals WHERE fragment_a=? AND fragment_b=?", (a, b)).fetchone()
        return _proposal(row) if row else None

    def ranked(self, fragment: str, limit: int = 20, *, status: str | None = None) -> list[Proposal]:
        """Proposals involving ``fragment``, best first (:data:`ORDER`)."""
        extra = " AND status=?" if status else ""
        args = (fragment,) + ((status,) if status else ())
        q = (f"SELECT * FROM (SELECT * FROM proposals WHERE fragment_a=?{extra} UNION ALL "
             f"SELECT * FROM proposals WHERE fragment_b=?{extra}) ORDER BY {ORDER} LIMIT ?")
        return [_proposal(r) for r in self._db.execute(q, args + args + (int(limit),))]

    def pending(self, limit: int = 100) -> list[Proposal]:
        """All pending proposals, best first (:data:`ORDER`)."""
        q = f"SELECT * FROM proposals WHERE status='pending' ORDER BY {ORDER} LIMIT ?"
        return [_proposal(r) for r in self._db.execute(q, (int(limit),))]

    def set_mutual(self, updates: list[tuple[str, str, float]]) -> int:
        """Set the mutual proximity of stored pairs ``(a, b, mutual)`` (either order); pairs not
        stored are skipped. Returns how many rows changed."""
        n = 0
        with self._tx():
            for a, b, m in updates:
                a, b = ordered_pair(a, b)
                n += self._db.execute("UPDATE proposals SET mutual=? WHERE fragment_a=? AND fragment_b=?",
                                      (float(m), a, b)).rowcount
        return n

    def all(self) -> list[Proposal]:
        return [_proposal(r) for r in self._db.execute("SELECT * FROM proposals ORDER BY id")]

    def count(self, status: str | None = None) -> int:
        if status:
            return self._db.execute("SELECT COUNT(*) FROM proposals WHERE status=?", (status,)).fetchone()[0]
        return self._db.execute("SELECT COUNT(*) FROM proposals").fetchone()[0]

    def set_probabilities(self, updates: list[tuple[int, float]], model_version: str) -> None:
        """Re-rank: new probabilities (proposal id, p) under ``model_version``, in one transaction."""
        now = time.time()
        with self._tx():
            self._db.executemany("UPDATE proposals SET probability=?, model_version=?, updated=? WHERE id=?",
                                 [(float(p), model_version, now, int(i)) for i, p in updates])

    # -- verdicts ------------------------------------------------------------------------
    def record_verdict(self, a: str, b: str, verdict: str, *, by: str | None = None, note: str | None = None,
                       message_uid: str | None = None, when: float | None = None,
                       pose: dict | None = None) -> Verdict | None:
        """Store a person's verdict on a pair and set the proposal's status.

        Idempotent per message: a re-delivered ``match.verified`` (same ``message_uid``) is
        ignored and returns None. The full history is kept; the latest verdict sets the status.
        ``pose``: the pose the person set (``b`` in ``a``'s frame: angle_deg, tx_mm, ty_mm), kept with
        the verdict instead of the proposal's.
        """
        if verdict not in VERDICTS:
            raise ValueError(f"verdict must be one of {VERDICTS}, got {verdict!r}")
        if pose is not None:
            from common.messages import MessageError, pose_of

            try:
                pose = pose_of(pose)
            except MessageError as exc:
                raise ValueError(str(exc)) from None
            if (a, b) != ordered_pair(a, b):   # stored as the second in the first's frame
                from common.matching.pose import inverse_pose

                pose = dict(zip(("angle_deg", "tx_mm", "ty_mm"), inverse_pose(*pose.values())))
        a, b = ordered_pair(a, b)
        when = time.time() if when is None else float(when)
        with self._tx():
            if message_uid is not None and self._db.execute(
                    "SELECT 1 FROM verdicts WHERE message_uid=?", (message_uid,)).fetchone():
                return None
            prop = self._db.execute("SELECT id, model_version, angle_deg, tx_mm, ty_mm FROM proposals "
                                    "WHERE fragment_a=? AND fragment_b=?", (a, b)).fetchone()
            # the pose the person saw (or set) is kept with the verdict: a later re-rank may move the proposal's
            if pose is None:
                pose = ({"angle_deg": prop["angle_deg"], "tx_mm": prop["tx_mm"], "ty_mm": prop["ty_mm"]}
                        if prop and prop["angle_deg"] is not None else None)
            cur = self._db.execute(
                "INSERT INTO verdicts (fragment_a, fragment_b, verdict, by, note, proposal_id, model_version, message_uid,"
                " time, pose) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (a, b, verdict, by, note, prop["id"] if prop else None, prop["model_version"] if prop else None,
                 message_uid, when, json.dumps(pose) if pose else None))
            if prop:
                self._db.execute("UPDATE proposals SET status=?, updated=? WHERE id=?", (verdict, when, prop["id"]))
            vid = cur.lastrowid
        return Verdict(a, b, verdict, when, by, note, prop["id"] if prop else None,
                       prop["model_version"] if prop else None, vid, pose)

    def verdicts(self, fragment: str | None = None) -> list[Verdict]:
        """Verdict history in time order (optionally only those involving ``fragment``)."""
        q = "SELECT * FROM verdicts" + (" WHERE fragment_a=? OR fragment_b=?" if fragment else "") + " ORDER BY time, id"
        rows = self._db.execute(q, (fragment, fragment) if fragment else ()).fetchall()
        return [_verdict(r) for r in rows]

    def latest_verdict(self, a: str, b: str) -> Verdict | None:
        """The latest verdict on the pair (either order), or None: the one that set its status, with the pose
        kept with it (``b`` in ``a``'s stored order: :func:`ordered_pair`)."""
        a, b = ordered_pair(a, b)
        r = self._db.execute("SELECT * FROM verdicts WHERE fragment_a=? AND fragment_b=? ORDER BY time DESC, id DESC "
                             "LIMIT 1", (a, b)).fetchone()
        return _verdict(r) if r is not None else None

    def latest_verdicts(self) -> dict[tuple[str, str], str]:
        """The latest verdict per pair (a person may change their mind)."""
        out = {}
        for v in self.verdicts():
            out[(v.fragment_a, v.fragment_b)] = v.verdict
        return out

    # -- dockings ------------------------------------------------------------------------
    def docking(self, a: str, b: str, inputs_a: str, inputs_b: str, docking_version: str) -> StoredDocking | None:
        """The stored docking of the pair (``a < b``) made from exactly these inputs by this docking version,
        or None: none stored, one made from other inputs or by another version, or a row that does not
        decode (a damaged row is as good as none: the pair is docked again and the row replaced)."""
        if (a, b) != ordered_pair(a, b):
            raise ValueError("docking fragments must be in stored order: use ordered_pair()")
        row = self._db.execute("SELECT * FROM dockings WHERE fragment_a=? AND fragment_b=? AND inputs_a=? AND "
                               "inputs_b=? AND docking_version=?", (a, b, inputs_a, inputs_b, docking_version)).fetchone()
        if row is None:
            return None
        try:
            return _stored_docking(row)
        except (ValueError, TypeError, KeyError, IndexError):
            return None

    def put_docking(self, d: StoredDocking) -> None:
        """Store a pair's docking, replacing the pair's earlier one (made from other inputs or by another
        version, or the same: two workers that docked one pair store the same numbers, the last one stays)."""
        a, b = ordered_pair(d.fragment_a, d.fragment_b)
        if (a, b) != (d.fragment_a, d.fragment_b):
            raise ValueError("docking fragments must be in stored order: use ordered_pair()")
        best = _pose_numbers(d.best)
        with self._tx():
            self._db.execute(
                "INSERT OR REPLACE INTO dockings (fragment_a, fragment_b, inputs_a, inputs_b, docking_version, "
                + ", ".join(DOCKING_FIELDS) + ", paint, paint_mm, pose, alternatives, created) "
                "VALUES (" + ", ".join("?" * (5 + len(DOCKING_FIELDS) + 5)) + ")",
                (a, b, d.inputs_a, d.inputs_b, d.docking_version, *best, int(bool(d.paint)),
                 _real(d.paint_mm), json.dumps(_pose_numbers(d.pose)) if d.pose is not None else None,
                 json.dumps([_pose_numbers(p) for p in d.alternatives]), time.time()))

    def count_dockings(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM dockings").fetchone()[0]

    def dock_hubness(self, inputs: dict[str, str], docking_version: str) -> dict[str, float]:
        """The stored docking hubness (mean contact of a fragment's best dockings, mm) of the fragments of
        ``inputs`` (fragment → digest of its docking inputs) whose value was made from exactly those inputs
        by this docking version; the others are left out (as good as none)."""
        out: dict[str, float] = {}
        ids = list(inputs)
        for k in range(0, len(ids), 500):   # SQLite's bound-parameter limit
            chunk = ids[k:k + 500]
            rows = self._db.execute("SELECT fragment, inputs, docking_version, contact_mm FROM dock_hubness WHERE "
                                    f"fragment IN ({', '.join('?' * len(chunk))})", chunk).fetchall()
            for r in rows:
                if r["inputs"] == inputs[r["fragment"]] and r["docking_version"] == docking_version \
                        and r["contact_mm"] is not None and math.isfinite(r["contact_mm"]):
                    out[r["fragment"]] = float(r["contact_mm"])
        return out

    def put_dock_hubness(self, fragment: str, inputs: str, docking_version: str, contact_mm: float,
                         model_version: str | None = None) -> None:
        """Store a fragment's docking hubness (mm), replacing its earlier value: the last worker to rank
        the fragment sets it, and every worker reads it (``model_version``: the model it was ranked under)."""
        with self._tx():
            self._db.execute("INSERT OR REPLACE INTO dock_hubness (fragment, inputs, docking_version, contact_mm, "
                             "model_version, created) VALUES (?, ?, ?, ?, ?, ?)",
                             (fragment, inputs, docking_version, float(contact_mm), model_version, time.time()))

    # -- models --------------------------------------------------------------------------
    def add_model(self, version: str, artifact: dict, *, n_train: int | None = None, note: str | None = None,
                  make_current: bool = True) -> None:
        with self._tx():
            self._db.execute("INSERT OR IGNORE INTO models VALUES (?, ?, ?, ?, ?, ?, ?)",
                             (version, artifact["path"], artifact["sha256"], int(artifact["bytes"]), time.time(),
                              n_train, note))
            if make_current:
                self._db.execute("INSERT INTO meta(key, value) VALUES('current_model', ?) "
                                 "ON CONFLICT(key) DO UPDATE SET value=excluded.value", (version,))

    def current_model(self) -> dict | None:
        """The current model's version and artifact pointer, or None before the first model."""
        version = self.get_meta("current_model")
        if version is None:
            return None
        r = self._db.execute("SELECT * FROM models WHERE version=?", (version,)).fetchone()
        return {"version": r["version"], "n_train": r["n_train"], "note": r["note"],
                "artifact": {"path": r["artifact"], "sha256": r["sha256"], "bytes": r["bytes"]}}

    def models(self) -> list[dict]:
        return [dict(r) for r in self._db.execute("SELECT * FROM models ORDER BY created")]


def _proposal(r: sqlite3.Row) -> Proposal:
    return Proposal(fragment_a=r["fragment_a"], fragment_b=r["fragment_b"], probability=r["probability"],
                    model_version=r["model_version"], patch_a=r["patch_a"], patch_b=r["patch_b"],
                    angle_deg=r["angle_deg"], tx_mm=r["tx_mm"], ty_mm=r["ty_mm"],
                    alignment=json.loads(r["alignment"]) if r["alignment"] else None,
                    evidence=json.loads(r["evidence"]) if r["evidence"] else None,
                    status=r["status"], id=r["id"], created=r["created"], updated=r["updated"],
                    mutual=r["mutual"])


def _verdict(r: sqlite3.Row) -> Verdict:
    return Verdict(r["fragment_a"], r["fragment_b"], r["verdict"], r["time"], r["by"], r["note"], r["proposal_id"],
                   r["model_version"], r["id"], json.loads(r["pose"]) if r["pose"] else None)


def _real(x) -> float | None:
    """A number for a REAL column: NaN as NULL (SQLite stores no NaN)."""
    x = float(x)
    return x if x == x else None


def _pose_numbers(pose) -> list:
    """A docked pose's numbers (:data:`DOCKING_FIELDS`) with NaN as None (NULL, JSON null)."""
    numbers = [_real(x) for x in pose]
    if len(numbers) != len(DOCKING_FIELDS):
        raise ValueError(f"a docked pose has {len(DOCKING_FIELDS)} numbers ({', '.join(DOCKING_FIELDS)}), got {len(numbers)}")
    return numbers



def _pose_tuple(numbers) -> tuple:
    """The inverse of :func:`_pose_numbers`: floats, NULL as NaN; anything else fails (a damaged row)."""
    if not isinstance(numbers, (list, tuple)) or len(numbers) != len(DOCKING_FIELDS):
        raise ValueError(f"not a docked pose: {numbers!r}")
    return tuple(float("nan") if x is None else float(x) for x in numbers)


def _stored_docking(r: sqlite3.Row) -> StoredDocking:
    paint = bool(int(r["paint"]))
    pose = json.loads(r["pose"]) if r["pose"] is not None else None
    if paint and pose is None:
        raise ValueError("a docking with paint without its pose")
    alternatives = json.loads(r["alternatives"]) if r["alternatives"] else []
    if not isinstance(alternatives, list):
        raise ValueError("alternatives are not a list")
    return StoredDocking(r["fragment_a"], r["fragment_b"], r["inputs_a"], r["inputs_b"], r["docking_version"],
                         best=_pose_tuple([r[k] for k in DOCKING_FIELDS]), paint=paint,
                         paint_mm=float("nan") if r["paint_mm"] is None else float(r["paint_mm"]),
                         pose=_pose_tuple(pose) if pose is not None else None,
                         alternatives=[_pose_tuple(p) for p in alternatives], created=float(r["created"]))
