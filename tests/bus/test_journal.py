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
