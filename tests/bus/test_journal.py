"""The broker's journal writer: one operation SQLite cannot hold never stops it (issue 19)."""

from __future__ import annotations

import sqlite3

import zmq

from common.bus.journal import Journal


def _durable(signal, timeout_ms=5000) -> bytes:
    assert signal.poll(timeout_ms), "the writer reported nothing"
    return signal.recv()


def test_an_operation_sqlite_refuses_is_skipped_and_the_writer_goes_on(tmp_path):
    ctx = zmq.Context()
    signal = ctx.socket(zmq.PAIR)
    signal.bind("inproc://journal-test")
    journal = Journal(tmp_path, history=100)
    journal.load()
    journal.start(ctx, "inproc://journal-test")
    try:
        # the uid 2**64-1 that killed the writer (OverflowError) in the attack run
        journal.append(1, [("event", 1, 2 ** 64 - 1, "noop.job", 1.0, b"x"), ("event", 2, "a" * 32, "noop.job", 1.0, b"y"),
                           ("job", "j2", 2, "noop")])
        assert _durable(signal) == b"1"
        journal.append(2, [("event", 3, "b" * 32, "noop.job", 1.0, b"z")])
        assert _durable(signal) == b"2", "the next batch is durable too: the writer is alive"
    finally:
        journal.stop()
        signal.close(linger=0)
        ctx.term()
    con = sqlite3.connect(tmp_path / "journal.sqlite")
    assert [r[0] for r in con.execute("SELECT seq FROM events ORDER BY seq")] == [2, 3]
    assert [r[0] for r in con.execute("SELECT id FROM jobs")] == ["j2"]
    con.close()


def test_output_keys_survive_a_restart(tmp_path):
    ctx = zmq.Context()
    signal = ctx.socket(zmq.PAIR)
    signal.bind("inproc://journal-test2")
    journal = Journal(tmp_path)
    journal.load()
    journal.start(ctx, "inproc://journal-test2")
    try:
        journal.append(1, [("event", 1, "c" * 32, "rgbn.ready", 1.0, b"x"), ("output", "k1", 1)])
        assert _durable(signal) == b"1"
    finally:
        journal.stop()
        signal.close(linger=0)
        ctx.term()
    assert Journal(tmp_path).load().outputs == {"k1"}


# -- the disk or the file refusing: the broker must hear of it, and the writer must not die of compaction --

import logging  # noqa: E402
import time  # noqa: E402

from .test_worker import _mount_tmpfs, fill_disk, mounts  # noqa: E402,F401  (the tmpfs of the full-disk tests)


def test_compaction_on_a_full_disk_is_retried_and_the_writer_goes_on(tmp_path, mounts, caplog):
    """docs/storage.md: on a full disk the writer keeps going and the broker accepts again once space
    is freed. A compaction refused by the full disk ended the writer (FAILED, for good)."""
    journal_dir = tmp_path / "journal"
    _mount_tmpfs(journal_dir, size="2m")
    mounts.append(journal_dir)
    ctx = zmq.Context()
    signal = ctx.socket(zmq.PAIR)
    signal.bind("inproc://journal-full")
    journal = Journal(journal_dir, history=2, compact_interval_s=1.0)
    journal.load()
    journal.start(ctx, "inproc://journal-full")
    caplog.set_level(logging.INFO, logger="tessera.journal")
    try:
        journal.append(1, [("event", s, f"{s:032x}", "noop.job", 1.0, b"x" * 1000) for s in range(1, 11)])
        assert _durable(signal) == b"1"
        fill_disk(journal_dir)  # before the first compaction (1 s after the start): it meets the full disk
        assert not signal.poll(2500), "the writer reported FAILED: a refused compaction ended it"
        assert "compaction failed" in caplog.text and "disk is full" in caplog.text
        assert [s for s, _ in journal.events_since(0, 100, 100)] == list(range(1, 11)), "nothing lost"
        (journal_dir / "ballast").unlink()
        journal.append(2, [("event", 11, "b" * 32, "noop.job", 1.0, b"y")])
        assert _durable(signal) == b"2", "the writer commits again once space is freed"
        deadline = time.monotonic() + 5
        while journal.first_seq() != 10 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert [s for s, _ in journal.events_since(0, 100, 100)] == [10, 11], "compacted at a later period"
    finally:
        journal.stop()
        signal.close(linger=0)
        ctx.term()


def test_a_malformed_database_is_reported_not_spun_on(tmp_path, caplog):
    """A malformed database refuses every batch, however few its operations: that is not an
    operation SQLite cannot hold, so none is skipped. The writer reports FAILED (the broker refuses
    submissions) with the error in the log; it wrote each operation alone, found them all good and
    tried the batch again, thousands of times a second, reporting nothing."""
    ctx = zmq.Context()
    signal = ctx.socket(zmq.PAIR)
    signal.bind("inproc://journal-malformed")
    journal = Journal(tmp_path, history=100)
    journal.load()
    path = tmp_path / "journal.sqlite"
    con = sqlite3.connect(path)
    pages = [p for (p,) in con.execute("SELECT rootpage FROM sqlite_schema WHERE tbl_name = 'meta'")]
    page_size = con.execute("PRAGMA page_size").fetchone()[0]
    con.close()
    with open(path, "r+b") as fh:  # the meta table, written with every batch (last_seq), is garbage
        for page in pages:
            fh.seek((page - 1) * page_size)
            fh.write(b"\xff" * page_size)
    journal.start(ctx, "inproc://journal-malformed")
    thread = journal._thread
    caplog.set_level(logging.INFO, logger="tessera.journal")
    try:
        journal.append(1, [("event", 1, "a" * 32, "noop.job", 1.0, b"x"), ("job", "j1", 1, "noop")])
        assert _durable(signal) == b"FAILED"
        thread.join(2.0)
        assert not thread.is_alive(), "the writer still runs on a malformed database"
        assert "malformed" in caplog.text and "skipped" not in caplog.text
    finally:
        journal.stop(timeout=1.0)
        ctx.destroy(linger=0)  # the writer's socket too, should it still run


def test_a_journal_the_writer_cannot_open_is_reported(tmp_path, monkeypatch, caplog):
    """The writer opened its connection before its ``try``: a journal it could not open (the file
    replaced, its folder's permissions changed, descriptors exhausted) ended the thread silently and
    the broker waited for acknowledgements that never came, instead of refusing submissions."""
    import threading

    from common.bus import journal as journal_module

    ctx = zmq.Context()
    signal = ctx.socket(zmq.PAIR)
    signal.bind("inproc://journal-unopenable")
    journal = Journal(tmp_path, history=100)
    journal.load()

    def refuse(path):
        raise sqlite3.OperationalError("unable to open database file")

    monkeypatch.setattr(journal_module, "_connect", refuse)
    caplog.set_level(logging.INFO, logger="tessera.journal")
    thread = None
    try:
        journal._thread = thread = threading.Thread(
            target=journal._writer, args=(ctx, "inproc://journal-unopenable"), daemon=True)
        thread.start()
        assert _durable(signal) == b"FAILED"
        thread.join(2.0)
        assert not thread.is_alive() and "unable to open database file" in caplog.text
    finally:
        journal._queue.put(None)
        if thread is not None:
            thread.join(2.0)
        ctx.destroy(linger=0)
