"""The broker's journal: SQLite on the broker's local disk, written with group commit.

Every accepted event and every job it creates is written here, and the broker acknowledges or
publishes only after the transaction holding it is durable (``synchronous=FULL``: the WAL is
fsynced at commit). One writer thread takes everything the poll loop produced since its last
commit and writes it in one transaction, so a burst of 2,000 messages costs one fsync, not 2,000.
The broker never waits on the disk: the writer reports each durable batch id over an inproc
socket.

Tables
------
``meta(key, value)``             stream id of this journal.
``events(seq, uid, type, time, body)``  every event in feed order; kept for ``feed_history`` events
                                 (and as long as a pending job needs it) for subscribers catching up.
``jobs(id, seq, service, state, failures, error)``  pending (``queued``) and ``parked`` jobs; a
                                 finished job's row is deleted. In-flight jobs are ``queued`` on disk,
                                 so a broker restart re-queues them.
``outputs(key, seq)``            identity of every output event a worker announced (a digest of the
                                 event without ``uid`` and ``time``): the same output is never
                                 announced twice, across restarts too.

A batch the database cannot take (disk full, I/O error) is retried every second; the broker is
told (``FAILED``) and refuses submissions until a batch is durable again. An operation SQLite
refuses on its own (a value it cannot hold) is logged and skipped; the others are written.

Compaction deletes events beyond the history and checkpoints the WAL, so the journal's size is
bounded by the history and the backlog, not by the station's lifetime. A compaction the disk refuses
is logged and tried again next period; it never stops the writer. A malformed database is reported
(``FAILED``), never retried or skipped around.
"""

from __future__ import annotations

import logging
import queue
import sqlite3
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import zmq

log = logging.getLogger("tessera.journal")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS events (seq INTEGER PRIMARY KEY, uid TEXT NOT NULL, type TEXT NOT NULL,
                                   time REAL NOT NULL, body BLOB NOT NULL);
CREATE INDEX IF NOT EXISTS events_uid ON events(uid);
CREATE TABLE IF NOT EXISTS jobs (id TEXT PRIMARY KEY, seq INTEGER NOT NULL, service TEXT NOT NULL,
                                 state TEXT NOT NULL, failures INTEGER NOT NULL DEFAULT 0,
                                 error TEXT NOT NULL DEFAULT '');
CREATE TABLE IF NOT EXISTS outputs (key TEXT PRIMARY KEY, seq INTEGER NOT NULL);
"""


@dataclass
class JournalState:
    """What a broker restores at start: stream id, last sequence, pending and parked jobs."""

    stream: str
    last_seq: int
    jobs: list = field(default_factory=list)        # (id, seq, service, state, failures, error, body)
    uids: list = field(default_factory=list)        # (uid, seq) of retained events, oldest first
    outputs: set = field(default_factory=set)       # keys of output events already announced


def _disk_refused(exc: BaseException) -> bool:
    """True if SQLite refused a write because of the disk, not the data (full, read-only, locked, I/O
    error): the same write succeeds once the disk takes writes again, so it is kept and retried. Every
    ``OperationalError`` counts: the rarer ones retrying cannot fix (a table gone) are still reported to
    the broker (``FAILED``) and retried once a second, never skipped op by op or spun on."""
    return isinstance(exc, sqlite3.OperationalError)


def _database_broken(exc: BaseException) -> bool:
    """True if the database file itself is unusable (malformed, not a database: SQLite's errors Python
    raises as a plain ``DatabaseError``): every batch would be refused again, however few its
    operations, so skipping operations cannot help and the failure must be reported."""
    return type(exc) is sqlite3.DatabaseError


def _connect(path: Path) -> sqlite3.Connection:
    con = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30)
    con.execute("PRAGMA journal_mode=WAL")
    con.execute("PRAGMA synchronous=FULL")
    return con


class Journal:
    """Durable record of the broker's accepted events and jobs.

    Parameters
    ----------
    directory : path
        Local directory (not NFS: fsync and locking semantics matter) holding ``journal.sqlite``.
    history : int
        Events kept for subscribers that catch up after a disconnection.
    compact_interval_s : float
        Period of compaction.
    """

    def __init__(self, directory, *, history: int = 100000, compact_interval_s: float = 60.0):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.path = self.dir / "journal.sqlite"
        self.history = int(history)
        self.compact_interval_s = float(compact_interval_s)
        self._queue: queue.Queue = queue.Queue()
        self._thread: threading.Thread | None = None
        self._reader = None
        self._last_seq_written = 0
        self.batches_committed = 0

    # -- start-up --------------------------------------------------------------------------
    def load(self) -> JournalState:
        """Create the tables if needed and read back the state a restarted broker resumes."""
        con = _connect(self.path)
        try:
            con.executescript(_SCHEMA)
            row = con.execute("SELECT value FROM meta WHERE key='stream'").fetchone()
            if row is None:
                stream = uuid.uuid4().hex[:12]
                con.execute("INSERT INTO meta VALUES ('stream', ?)", (stream,))
            else:
                stream = row[0]
            last = con.execute("SELECT COALESCE(MAX(seq), 0) FROM events").fetchone()[0]
            stored = con.execute("SELECT value FROM meta WHERE key='last_seq'").fetchone()
            if stored is not None:  # sequence numbers never go back, even when old events are compacted away
                last = max(last, int(stored[0]))
            jobs = con.execute(
                "SELECT j.id, j.seq, j.service, j.state, j.failures, j.error, e.body FROM jobs j "
                "JOIN events e ON e.seq = j.seq ORDER BY j.seq, j.id").fetchall()
            uids = con.execute("SELECT uid, seq FROM events ORDER BY seq DESC LIMIT ?", (self.history,)).fetchall()
            outputs = {k for (k,) in con.execute("SELECT key FROM outputs")}
        finally:
            con.close()
        self._last_seq_written = last
        return JournalState(stream=stream, last_seq=int(last), jobs=jobs, uids=list(reversed(uids)), outputs=outputs)

    def start(self, context: zmq.Context, signal_endpoint: str) -> None:
        """Start the writer thread; it reports durable batch ids on ``signal_endpoint`` (inproc PAIR)."""
        self._thread = threading.Thread(target=self._writer, args=(context, signal_endpoint),
                                        name="journal-writer", daemon=True)
        self._thread.start()
        self._reader = _connect(self.path)

    def append(self, batch_id: int, ops: list) -> None:
        """Queue one poll-loop batch of operations; ``batch_id`` is reported once it is durable.

        Operations: ``("event", seq, uid, type, time, body)``, ``("job", id, seq, service)``,
        ``("done", id)``, ``("fail", id, failures, error)``, ``("park", id, failures, error)``,
        ``("requeue", id)``, ``("output", key, seq)``.
        """
        self._queue.put((batch_id, ops))

    def stop(self, timeout: float = 10.0) -> None:
        """Flush what is queued and stop the writer."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout)
            self._thread = None
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    # -- reading (broker thread) -----------------------------------------------------------
    def events_since(self, after: int, limit: int, upto: int, types: list[str] | None = None
                     ) -> list[tuple[int, bytes]]:
        """Retained events with ``after < seq <= upto`` (of ``types`` only, if given), oldest first,
        at most ``limit``."""
        if types:
            marks = ",".join("?" * len(types))
            rows = self._reader.execute(f"SELECT seq, body FROM events WHERE seq > ? AND seq <= ? AND type IN ({marks}) "
                                        "ORDER BY seq LIMIT ?", (int(after), int(upto), *types, int(limit))).fetchall()
        else:
            rows = self._reader.execute("SELECT seq, body FROM events WHERE seq > ? AND seq <= ? ORDER BY seq LIMIT ?",
                                        (int(after), int(upto), int(limit))).fetchall()
        return [(int(s), bytes(b)) for s, b in rows]

    def first_seq(self) -> int:
        """Oldest retained sequence number (0 when empty)."""
        return int(self._reader.execute("SELECT COALESCE(MIN(seq), 0) FROM events").fetchone()[0])

    def size_bytes(self) -> int:
        """Bytes on disk (database + WAL)."""
        return sum(p.stat().st_size for p in self.dir.glob("journal.sqlite*") if p.exists())

    # -- the writer thread -----------------------------------------------------------------
    def _writer(self, context: zmq.Context, signal_endpoint: str) -> None:
        signal = context.socket(zmq.PAIR)
        signal.connect(signal_endpoint)
        last_compact = time.monotonic()
        stopping = False
        con = None
        try:
            con = _connect(self.path)   # inside: a journal that cannot be opened is reported like any failure
            while not stopping:
                try:
                    first = self._queue.get(timeout=0.5)
                except queue.Empty:
                    first = ()
                items = [first] if first != () else []
                while True:  # group commit: everything queued so far goes into one transaction
                    try:
                        items.append(self._queue.get_nowait())
                    except queue.Empty:
                        break
                if None in items:
                    stopping = True
                    items = [i for i in items if i is not None]
                if items:
                    self._commit(con, [op for _batch_id, ops in items for op in ops], signal)
                    self.batches_committed += 1
                    signal.send(str(items[-1][0]).encode())
                if time.monotonic() - last_compact > self.compact_interval_s:
                    self._compact(con)
                    last_compact = time.monotonic()
        except Exception:  # the broker cannot acknowledge anything without its journal: say so loudly
            log.exception("journal writer failed; the broker stops acknowledging")
            signal.send(b"FAILED")
        finally:
            signal.close(linger=0)
            if con is not None:
                con.close()

    def _commit(self, con: sqlite3.Connection, ops: list, signal) -> None:
        """Write ``ops`` in one transaction; never give up on the journal because of one of them.

        The database refusing everything (disk full, I/O error) is retried every second after
        telling the broker (``FAILED``); an operation refused on its own is skipped, logged. A
        malformed database is raised: the writer reports it (``FAILED``) instead of retrying a batch
        that can never be written.
        """
        failed = False
        while True:
            try:
                con.execute("BEGIN")
                self._apply(con, ops)
                con.execute("INSERT OR REPLACE INTO meta VALUES ('last_seq', ?)", (str(self._last_seq_written),))
                con.execute("COMMIT")
                if failed:
                    log.warning("journal writable again: the broker acknowledges events again")
                return
            except Exception as exc:
                self._rollback(con)
                if _database_broken(exc):
                    raise
                if not _disk_refused(exc):  # a value SQLite cannot hold: write the others one by one
                    ops = self._operations_taken(con, ops, exc)
                    continue
                # the disk, not the data: wait until it takes writes
                if not failed:
                    log.error("journal write failed (%s): retrying every second; the broker refuses submissions", exc)
                    signal.send(b"FAILED")
                    failed = True
                time.sleep(1.0)

    def _operations_taken(self, con: sqlite3.Connection, ops: list, exc: Exception) -> list:
        """The operations of a refused batch SQLite takes on their own; the others are logged and skipped."""
        log.error("journal batch refused (%s: %s): writing its %d operations one by one",
                  type(exc).__name__, exc, len(ops))
        good = []
        for op in ops:
            try:
                con.execute("SAVEPOINT one")
                self._apply(con, [op])
                con.execute("ROLLBACK TO one")
                good.append(op)
            except Exception as one:
                if _disk_refused(one) or _database_broken(one):  # not this operation's fault
                    raise
                con.execute("ROLLBACK TO one")
                log.error("journal operation %r skipped: %s", str(op)[:200], one)
            finally:
                con.execute("RELEASE one")
        return good

    @staticmethod
    def _rollback(con: sqlite3.Connection) -> None:
        try:
            con.execute("ROLLBACK")
        except sqlite3.Error:
            pass

    def _apply(self, con: sqlite3.Connection, ops: list) -> None:
        # Grouped by kind, in an order that gives the same end state as the original sequence:
        # a job is inserted before it is updated, updated (in order) before it is deleted.
        events, jobs, updates, done, outputs = [], [], [], [], []
        for op in ops:
            kind = op[0]
            if kind == "event":
                events.append(op[1:])
            elif kind == "output":
                outputs.append(op[1:])
            elif kind == "job":
                jobs.append(op[1:])
            elif kind == "done":
                done.append((op[1],))
            elif kind in ("fail", "park", "requeue"):
                updates.append(op)
            else:
                raise ValueError(f"unknown journal operation {kind!r}")
        if events:
            con.executemany("INSERT OR IGNORE INTO events VALUES (?, ?, ?, ?, ?)", events)
            self._last_seq_written = max(self._last_seq_written, max(e[0] for e in events))
        if outputs:
            con.executemany("INSERT OR IGNORE INTO outputs VALUES (?, ?)", outputs)
        if jobs:
            con.executemany("INSERT OR IGNORE INTO jobs (id, seq, service, state) VALUES (?, ?, ?, 'queued')", jobs)
        for op in updates:
            if op[0] == "fail":
                con.execute("UPDATE jobs SET failures = ?, error = ?, state = 'queued' WHERE id = ?", (op[2], op[3], op[1]))
            elif op[0] == "park":
                con.execute("UPDATE jobs SET failures = ?, error = ?, state = 'parked' WHERE id = ?", (op[2], op[3], op[1]))
            else:
                con.execute("UPDATE jobs SET failures = 0, state = 'queued' WHERE id = ?", (op[1],))
        if done:
            con.executemany("DELETE FROM jobs WHERE id = ?", done)

    def _compact(self, con: sqlite3.Connection) -> None:
        """Drop events beyond the history that no pending job needs, and truncate the WAL.

        Compaction needs the disk too: refused (full, read-only, locked), it is logged and tried
        again next period while the writer goes on. The DELETE is one statement, so a refused one
        drops nothing.
        """
        keep_after = self._last_seq_written - self.history
        try:
            cur = con.execute("DELETE FROM events WHERE seq <= ? AND seq NOT IN (SELECT seq FROM jobs)", (keep_after,))
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        except Exception as exc:
            if not _disk_refused(exc):
                raise
            self._rollback(con)  # nothing may stay open for the next batch's BEGIN
            log.warning("journal compaction failed (%s): trying again in %g s", exc, self.compact_interval_s)
            return
        if cur.rowcount:
            log.info("journal compacted: %d old events dropped", cur.rowcount)
