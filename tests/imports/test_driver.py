"""The shared import driver: content keys, the ledger (resumable, nothing twice), refusals, summary."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from common.imports import ImportItem, ImportRefused, Ledger, Output, ProgressBar, StoreSink, run_import
from common.store import Store


def _items(tmp_path, n):
    items = []
    for i in range(n):
        src = tmp_path / "in" / f"f{i}.bin"
        src.parent.mkdir(exist_ok=True)
        src.write_bytes(np.random.default_rng(i).bytes(64))
        items.append(ImportItem(name=src.name, sources=[src], fragment=f"F{i:03d}"))
    return items


def _convert(calls, fail_on=(), interrupt_on=None):
    def convert(item, store):
        if item.fragment == interrupt_on:
            raise KeyboardInterrupt
        calls.append(item.fragment)
        if item.fragment in fail_on:
            raise ImportRefused(f"{item.name}: blank image")
        data = np.frombuffer(open(item.sources[0], "rb").read(), np.uint8)
        ref = store.write(f"fragments/{item.fragment}/test/{item.key}.h5", "test", 1,
                          lambda f: f.create_dataset("x", data=data))
        return [Output("rgbn.ready", ref, {"face": item.face})]
    return convert


def test_interrupted_import_resumes_and_imports_nothing_twice(tmp_path):
    items = _items(tmp_path, 6)
    sink = StoreSink(Store(tmp_path / "store"))
    calls = []
    first = run_import(items, _convert(calls, interrupt_on="F003"), sink, kind="t", version="1")
    assert first.interrupted and first.exit_status == 130
    assert first.imported == ["f0.bin", "f1.bin", "f2.bin"]
    again = run_import(_items(tmp_path, 6), _convert(calls), sink, kind="t", version="1")
    assert again.imported == ["f3.bin", "f4.bin", "f5.bin"]
    assert again.skipped == ["f0.bin", "f1.bin", "f2.bin"]
    assert sorted(calls) == [f"F{i:03d}" for i in range(6)]   # every item converted exactly once
    ledger = (tmp_path / "store" / "imports" / "ledger.jsonl").read_text().splitlines()
    assert len(ledger) == 6
    assert len(list((tmp_path / "store" / "fragments").rglob("*.h5"))) == 6


def test_changed_file_gets_a_new_key_and_is_imported_again(tmp_path):
    items = _items(tmp_path, 2)
    sink = StoreSink(Store(tmp_path / "store"))
    run_import(items, _convert([]), sink, kind="t", version="1")
    (tmp_path / "in" / "f1.bin").write_bytes(b"changed")
    again = [ImportItem(f"f{i}.bin", [tmp_path / "in" / f"f{i}.bin"], f"F{i:03d}") for i in range(2)]
    s = run_import(again, _convert([]), sink, kind="t", version="1")
    assert s.skipped == ["f0.bin"] and s.imported == ["f1.bin"]


def test_refused_items_are_reported_and_retried_next_run(tmp_path):
    items = _items(tmp_path, 3)
    sink = StoreSink(Store(tmp_path / "store"))
    s = run_import(items, _convert([], fail_on={"F001"}), sink, kind="t", version="1")
    assert s.imported == ["f0.bin", "f2.bin"]
    assert s.refused == [("f1.bin", "f1.bin: blank image")]
    assert s.exit_status == 1
    assert any("refused f1.bin: f1.bin: blank image" in line for line in s.lines())
    assert not (tmp_path / "store" / "fragments" / "F001").exists()   # nothing half-written
    s2 = run_import(_items(tmp_path, 3), _convert([]), sink, kind="t", version="1")
    assert s2.imported == ["f1.bin"] and s2.exit_status == 0


def test_missing_source_is_refused_naming_it(tmp_path):
    item = ImportItem("gone.png", [tmp_path / "gone.png"], "F1")
    s = run_import([item], _convert([]), StoreSink(Store(tmp_path / "store")), kind="t", version="1")
    assert s.refused and "gone.png" in s.refused[0][1]


def test_ledger_ignores_a_torn_last_line(tmp_path):
    path = tmp_path / "ledger.jsonl"
    path.write_text(json.dumps({"key": "a"}) + "\n" + '{"key": "b", "na')
    led = Ledger(path)
    assert "a" in led and "b" not in led
    led.add({"key": "c"})
    assert "c" in Ledger(path) and "a" in Ledger(path)


def test_progress_bar_reports_every_item():
    stream = io.StringIO()
    bar = ProgressBar(2, "import t", stream=stream)
    bar.update(1, "a.png")
    bar.update(2, "b.png")
    bar.close()
    text = stream.getvalue()
    assert "1/2 a.png" in text and "100.0%" in text
    with pytest.raises(ValueError, match="total"):
        ProgressBar(-1)


def test_an_event_the_schema_refuses_is_a_refusal_not_a_crash(tmp_path):
    item = _items(tmp_path, 1)[0]
    item.fragment = "bad id"           # a valid directory name, not a valid fragment id in a message
    s = run_import([item], _convert([]), StoreSink(Store(tmp_path / "store")), kind="t", version="1")
    assert s.refused and "cannot announce it" in s.refused[0][1]
    assert not (tmp_path / "store" / "imports" / "ledger.jsonl").exists()


def test_a_storage_error_falls_back_to_the_next_store(tmp_path):
    """Shared storage full or read-only mid-import: the item goes to the spool (the sink's next store)."""
    from common.store import StorageFull

    shared, spool = Store(tmp_path / "shared"), Store(tmp_path / "spool")
    emitted = []

    class TwoStores:
        ledger_dir = tmp_path / "ledger"

        def stores(self):
            return [shared, spool]

        def emit(self, event, ref, store):
            emitted.append((event["type"], ref.path, store is spool))
            return True

    inner = _convert([])

    def convert(item, store):
        if store is shared:
            raise StorageFull(f"no space left on {store.root}")
        return inner(item, store)

    s = run_import(_items(tmp_path, 2), convert, TwoStores(), kind="t", version="1")
    assert s.imported == ["f0.bin", "f1.bin"] and s.events == 2
    assert [e[2] for e in emitted] == [True, True]
    assert all(spool.exists(e[1]) and not shared.exists(e[1]) for e in emitted)
