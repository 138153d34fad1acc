"""The bench's spool and durable outbox: capture never blocks on the lab.

The scanner writes its scans to shared storage when it is reachable, else to a local **spool**
(a :class:`~common.store.Store` on the bench's own disk, same relative paths). Every event it
emits goes first into the **outbox**, an SQLite table on local disk committed with
``synchronous=FULL`` (fsynced), and is removed only after the broker acknowledged it. A drain
walks the outbox in order: upload the entry's spooled artifact (copy, fsync, digest check,
link), submit the event, delete the entry; it stops at the first entry that cannot be done
yet, so order is kept and nothing is lost when the broker or the storage is down. Storage that
refuses the upload (full, read-only) and a broker that cannot journal just now are "not yet"
too. An event the broker refuses for good (invalid), or whose spooled artifact can never be
uploaded (missing from the spool, failing its sha256, or other bytes already on storage under its
name), is moved to the ``refused`` table with the reason — kept on the bench for a person to look
at, never silently dropped — so the entries behind it go on.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sqlite3
import threading
from pathlib import Path
from typing import Mapping

from common import messages
from common.bus.client import BrokerClient, BrokerRefused, BrokerUnavailable
from common.store import ArtifactError, Store, StorageUnavailable

log = logging.getLogger("tessera.outbox")


class Outbox:
    """Ordered, durable queue of events (and spooled artifacts) waiting for the lab.

    Parameters
    ----------
    directory : path
        Local directory (not the NFS share): holds ``outbox.sqlite`` and ``spool/``.

    Examples
    --------
    ::

        box = Outbox("tessera-data/spool")
        box.put(event, spooled=ref.path, sha256=ref.sha256)   # after writing the artifact into box.spool
        box.drain(client, storage)               # returns how many entries went out
    """

    def __init__(self, directory: str | os.PathLike):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.spool = Store(self.dir / "spool")
        self._lock = threading.Lock()
        self._con = sqlite3.connect(self.dir / "outbox.sqlite", isolation_level=None, check_same_thread=False)
        self._con.execute("PRAGMA journal_mode=WAL")
        self._con.execute("PRAGMA synchronous=FULL")
        self._con.execute("CREATE TABLE IF NOT EXISTS outbox (id INTEGER PRIMARY KEY AUTOINCREMENT, "
                          "body BLOB NOT NULL, spooled TEXT, sha256 TEXT)")
        self._con.execute("CREATE TABLE IF NOT EXISTS refused (id INTEGER PRIMARY KEY, body BLOB NOT NULL, "
                          "spooled TEXT, sha256 TEXT, error TEXT NOT NULL, time REAL NOT NULL)")

    def close(self) -> None:
        with self._lock:
            self._con.close()

    def put(self, event: Mapping, *, spooled: str | None = None, sha256: str | None = None) -> int:
        """Append an event (durable when this returns); ``spooled`` names an artifact in
        :attr:`spool` (relative path, digest ``sha256``: both or neither) to upload before the event is sent."""
        if (spooled is None) != (sha256 is None):
            raise ValueError(f"a spooled artifact needs its sha256 and a sha256 its artifact, got {spooled!r}, {sha256!r}")
        body = messages.pack(messages.validate(event))
        with self._lock:
            cur = self._con.execute("INSERT INTO outbox (body, spooled, sha256) VALUES (?, ?, ?)", (body, spooled, sha256))
            return int(cur.lastrowid)

    def pending(self) -> list[tuple[int, dict, str | None]]:
        """Entries waiting, oldest first: ``(id, event, spooled path or None)``.

        An entry that is not a valid message now (written by an older, laxer version) is listed
        as decoded, without validation; :meth:`drain` sets it aside when it comes to it.
        """
        with self._lock:
            rows = self._con.execute("SELECT id, body, spooled FROM outbox ORDER BY id").fetchall()
        out = []
        for i, b, s in rows:
            try:
                event = messages.unpack(b)
            except messages.MessageError:
                import msgpack
                try:
                    event = msgpack.unpackb(b, raw=False, strict_map_key=False)
                except Exception:  # noqa: BLE001 - msgpack raises several types for garbage
                    event = None
                event = event if isinstance(event, dict) else {}
            out.append((i, event, s))
        return out

    def refused(self) -> list[tuple[int, dict, str]]:
        """Entries set aside for good: ``(id, event, reason)``, kept for a person to see (refused
        by the broker, or their spooled artifact can never be uploaded)."""
        import msgpack
        with self._lock:
            rows = self._con.execute("SELECT id, body, error FROM refused ORDER BY id").fetchall()
        return [(i, msgpack.unpackb(b, raw=False, strict_map_key=False), e) for i, b, e in rows]

    def _set_aside(self, oid: int, reason: str) -> None:
        """Move an entry from the outbox to the refused table (its spooled artifact stays)."""
        with self._lock:
            self._con.execute("BEGIN")
            self._con.execute("INSERT INTO refused SELECT id, body, spooled, sha256, ?, strftime('%s','now') "
                              "FROM outbox WHERE id = ?", (reason, oid))
            self._con.execute("DELETE FROM outbox WHERE id = ?", (oid,))
            self._con.execute("COMMIT")

    def _upload(self, spooled: str, sha256: str, storage: Store) -> str | None:
        """Copy an entry's spooled artifact to ``storage``; the reason it never can, or None once there.

        Raises OSError while storage cannot take it just now (unreachable, full, read-only): the
        entry waits. A spool copy that is missing or fails its digest, or other bytes already on
        storage under its name, cannot be fixed by retrying, and would block every entry behind.
        """
        try:
            source = self.spool.path(spooled)
            storage.import_file(source, spooled, sha256)
        except StorageUnavailable:  # an ArtifactError too, but the share will come back
            raise
        except FileNotFoundError:
            if source.is_file():  # not the spool copy that is gone: storage's trouble
                raise
            return f"spooled artifact {spooled} is missing from the spool ({source})"
        except ArtifactError as exc:
            return f"spooled artifact {spooled} cannot be uploaded: {exc}"
        return None

    def __len__(self) -> int:
        with self._lock:
            return int(self._con.execute("SELECT COUNT(*) FROM outbox").fetchone()[0])

    def drain(self, client: BrokerClient, storage: Store) -> int:
        """Send what can be sent now, in order; returns the number of entries drained.

        Stops quietly at the first entry whose artifact cannot be uploaded (storage unreachable)
        or whose event the broker does not acknowledge (broker down); the next drain resumes there.
        An entry that can never go (its event refused for good, its spooled artifact never
        uploadable) is set aside into the ``refused`` table and counted as drained.
        """
        done = 0
        while True:
            with self._lock:
                row = self._con.execute("SELECT id, body, spooled, sha256 FROM outbox ORDER BY id LIMIT 1").fetchone()
            if row is None:
                return done
            oid, body, spooled, sha256 = row
            if spooled:
                if not storage.available():
                    log.debug("storage %s unreachable; %d entries wait", storage.root, len(self))
                    return done
                try:
                    problem = self._upload(spooled, sha256, storage)
                except OSError as exc:
                    log.info("upload of %s failed (%s); will retry", spooled, exc)
                    return done
                if problem:
                    log.error("outbox entry %d: %s; kept in the outbox's refused table", oid, problem)
                    self._set_aside(oid, problem)
                    done += 1
                    continue  # its spooled artifact, if any, stays in the spool with it
            try:
                client.submit(messages.unpack(body))
            except messages.MessageError as exc:  # written by an older, laxer version: not sendable
                log.error("outbox entry %d is not a valid message (%s); kept in the refused table", oid, exc)
                self._set_aside(oid, f"not a valid message: {exc}")
                done += 1
                continue
            except BrokerUnavailable:
                log.debug("broker unreachable; %d entries wait", len(self))
                return done
            except BrokerRefused as exc:
                if exc.retry:  # the broker's own trouble (journal cannot write): keep it, try later
                    log.warning("broker cannot take outbox entry %d now (%s); will retry", oid, exc)
                    return done
                log.error("broker refused outbox entry %d for good (%s); kept in the outbox's refused table",
                          oid, exc)
                self._set_aside(oid, str(exc))
                done += 1
                continue  # its spooled artifact stays in the spool with it
            with self._lock:
                self._con.execute("DELETE FROM outbox WHERE id = ?", (oid,))
            if spooled:
                with contextlib.suppress(FileNotFoundError, ArtifactError):
                    self.spool.path(spooled).unlink()
            done += 1
