"""Tests of common/web/bench.py: the operator hand-shake around the capture workflow."""

from dataclasses import dataclass

import pytest

from common.web.bench import BenchBusy, BenchSession, check_fragment_id, describe_error


@dataclass
class Step:
    index: int
    total: int
    face: str
    rotation: float
    instruction: str


def _steps():
    out = []
    for face in ("front", "back"):
        for k in range(4):
            i = len(out)
            text = ("Place the fragment face down" if i == 0 else
                    "Flip the fragment" if k == 0 else "Turn the fragment 90° clockwise")
            out.append(Step(i, 8, face, 90.0 * k, text))
    return out


class FakeScanner:
    """Counts scans and records which steps the operator released, in order."""

    def __init__(self, fail_at=None, error=None):
        self.scanned, self.acted, self.fail_at, self.error = [], [], fail_at, error

    def capture(self, fid, operator):
        for step in _steps():
            operator(step)
            if step.index == self.fail_at:
                raise self.error
            self.scanned.append((step.face, step.rotation))
        return {"fragment": fid, "scans": list(self.scanned)}


def _wait_step(session, index):
    for _ in range(200):
        st = session.state()
        if st["phase"] == "waiting" and st["step"]["index"] == index:
            return st
        session.wait_for_change(st["seq"], 0.025)
    raise AssertionError(f"step {index} not reached: {session.state()}")


def _wait_phase(session, phase, timeout=5.0):
    for _ in range(200):
        st = session.state()
        if st["phase"] == phase:
            return st
        session.wait_for_change(st["seq"], timeout / 200)
    raise AssertionError(f"phase {phase!r} not reached: {session.state()}")


def test_capture_waits_for_the_operator_before_every_scan_and_delivers():
    scanner = FakeScanner()
    delivered = []
    session = BenchSession(capture=scanner.capture, deliver=lambda fid, r: delivered.append((fid, r)) or {"sent": True},
                           act=lambda step: scanner.acted.append(step.index))
    session.start("F0001")
    for step in _steps():
        st = _wait_step(session, step.index)
        assert st["step"]["instruction"] == step.instruction
        # no scan before the operator confirms; a stale click for another step does nothing
        assert len(scanner.scanned) == step.index
        session.proceed(step.index + 1)
        assert session.state()["phase"] == "waiting"
        session.proceed(step.index)
    st = _wait_phase(session, "done")
    session.join(2)
    assert scanner.acted == list(range(8))
    assert len(scanner.scanned) == 8
    assert delivered and delivered[0][0] == "F0001"
    assert st["history"][0]["outcome"] == "sent"
    assert not st["busy"]


def test_every_state_names_its_session_so_a_restart_is_told_from_an_older_answer():
    """The page orders the answers it gets by (session, seq): seq grows within a session and starts
    again in a new one (the station restarted), which has another name."""
    def session():
        return BenchSession(capture=FakeScanner().capture, deliver=lambda fid, r: {"sent": True})

    first, restarted = session(), session()
    st = first.state()
    first.start("F0001")
    waiting = _wait_step(first, 0)
    assert waiting["session"] == st["session"] and waiting["seq"] > st["seq"]
    assert restarted.state()["session"] != st["session"]
    first.cancel()
    first.join(2)


def test_lab_unreachable_keeps_scans_and_says_so():
    scanner = FakeScanner()
    session = BenchSession(capture=scanner.capture, deliver=lambda fid, r: {"sent": False},
                           act=lambda step: None)
    session.start("F0002")
    for i in range(8):
        _wait_step(session, i)
        session.proceed(i)
    st = _wait_phase(session, "done")
    assert st["history"][0]["outcome"] == "kept"
    assert "sent automatically" in st["message"]


def test_a_second_capture_while_scanning_is_refused_and_cancel_frees_the_scanner():
    scanner = FakeScanner()
    session = BenchSession(capture=scanner.capture, deliver=lambda fid, r: {"sent": True})
    session.start("F0003")
    _wait_phase(session, "waiting")
    with pytest.raises(BenchBusy):
        session.start("F0004")
    session.cancel()
    st = _wait_phase(session, "cancelled")
    session.join(2)
    assert st["history"][0]["outcome"] == "cancelled"
    assert scanner.scanned == []
    session.start("F0004")  # the scanner is free again
    _wait_phase(session, "waiting")
    session.cancel()
    session.join(2)


def test_capture_error_reaches_the_operator_in_plain_language():
    class ScannerError(Exception):
        def __init__(self, msg, operator_message, status):
            super().__init__(msg)
            self.operator_message, self.status = operator_message, status

    err = ScannerError("sane: SANE_STATUS_COVER_OPEN", "The scanner lid is open. Close it and press Scan.",
                       "SANE_STATUS_COVER_OPEN")
    scanner = FakeScanner(fail_at=2, error=err)
    session = BenchSession(capture=scanner.capture, deliver=lambda fid, r: {"sent": True})
    session.start("F0005")
    for i in range(3):
        _wait_step(session, i)
        session.proceed(i)
    st = _wait_phase(session, "error")
    assert st["error"]["kind"] == "scanner"
    assert st["error"]["message"] == "The scanner lid is open. Close it and press Scan."
    assert "COVER_OPEN" in st["error"]["detail"]
    assert st["history"][0]["outcome"] == "failed"


def test_prescan_failure_and_success_are_reported():
    class NoFragmentError(Exception):
        operator_message = "No fragment on the glass. Place it and try again."

    calls = []

    def prescan(fid):
        calls.append(fid)
        if len(calls) == 1:
            raise NoFragmentError("empty platen")
        return {"png": b"\x89PNG...", "message": "Fragment found."}

    session = BenchSession(capture=None, deliver=None, prescan=prescan)
    st = session.prescan("F0006")
    assert st["phase"] == "error" and st["error"]["kind"] == "no_fragment"
    assert st["error"]["message"].startswith("No fragment")
    st = session.prescan("F0006")
    assert st["phase"] == "idle" and st["message"] == "Fragment found."
    assert session.prescan_png() == b"\x89PNG..."


def test_unexpected_errors_do_not_blame_the_operator():
    d = describe_error(KeyError("albedo"))
    assert d["kind"] == "internal" and "technician" in d["message"] and "KeyError" in d["detail"]


@pytest.mark.parametrize("bad", ["", " ", "../etc", "a/b", "-x", "x" * 65, None])
def test_fragment_ids_that_cannot_name_a_folder_are_refused(bad):
    with pytest.raises(ValueError, match="fragment_id"):
        check_fragment_id(bad)


def test_an_id_starting_with_punctuation_is_refused_saying_why():
    """docs/web.md, bench: IDs start with a letter or digit; the refusal said only "1-64 letters, digits,
    '.', '_' or '-'", which "-F1" and ".F1" are."""
    for bad in ("-F1", ".F1", "_F1"):
        with pytest.raises(ValueError, match="starting with a letter or digit"):
            check_fragment_id(bad)
    assert check_fragment_id("F" * 64) == "F" * 64


def test_fragment_id_is_stripped():
    assert check_fragment_id("  F-12.a_3 ") == "F-12.a_3"


def test_scanner_status_without_operator_text_gets_plain_language():
    from common.acquisition.errors import ScannerError

    d = describe_error(ScannerError("simulated device fault SANE_STATUS_JAMMED", status="SANE_STATUS_JAMMED"))
    assert d["kind"] == "scanner" and "jam" in d["message"] and "SANE" not in d["message"]


def test_the_bench_says_where_the_scans_are_when_only_the_broker_is_away(tmp_path, monkeypatch):
    # issue 19: with the lab's storage reachable and only the broker away, the scans are on the
    # lab's storage (not "kept on this machine"); with the storage away too, they are spooled here
    import common.acquisition.capture as capture
    from common.config import load_config
    from services.web.station import StationLink, build_bench
    from tests.conftest import free_port

    cfg = load_config(None, {"storage.root": str(tmp_path / "storage"), "scanner.spool_dir": str(tmp_path / "bench"),
                             "broker.port": free_port(), "broker.feed_port": free_port(),
                             "client.timeout_s": 0.2, "client.retries": 1})
    monkeypatch.setattr(capture, "write_scans", lambda store, fid, result: store.write(
        f"fragments/{fid}/scans/scans-k.h5", "tessera.scans", 1, lambda f: f.create_dataset("x", data=[1])))

    @dataclass
    class Result:
        fragment_id: str
        device: str = "sim"
        colour_only: bool = True

    link = StationLink(cfg)
    try:
        deliver = build_bench(cfg, link=link, scanner=object())._deliver
        out = deliver("F0003", Result("F0003"))
        assert not out["sent"] and not out["spooled"]
        assert link.storage.exists(out["artifact"])
        assert "on the lab's storage" in out["message"] and "kept on this machine" not in out["message"]
        monkeypatch.setattr(link.storage, "available", lambda: False)
        out = deliver("F0004", Result("F0004"))
        assert out["spooled"] and "message" not in out   # the session then says: kept on this machine
    finally:
        link.close()
