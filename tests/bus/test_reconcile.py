"""tessera reconcile and tessera status, as a user runs them."""

from __future__ import annotations

import subprocess
import sys

from common.bus.reconcile import missing_stages
from common.store import Store

from .conftest import REPO, collect, free_port


def _h5(store: Store, rel: str):
    return store.write(rel, "tessera.test", 1, lambda f: f.create_dataset("x", data=[1]))


def _storage(store: Store) -> dict:
    return {
        "scans_only": _h5(store, "fragments/F1/scans/scans-aaa.h5"),
        "rgbn_front": _h5(store, "fragments/F2/rgbn/front-bbb.h5"),
        "f2_scans": _h5(store, "fragments/F2/scans/scans-ccc.h5"),
        "f3": [_h5(store, f"fragments/F3/{d}/front-ddd.h5") for d in ("rgbn", "features", "renders")]
              + [_h5(store, "fragments/F3/scans/scans-eee.h5")],
    }


def test_missing_stages_finds_inputs_whose_outputs_are_absent(tmp_path):
    store = Store(tmp_path)
    refs = _storage(store)
    store.path("fragments/F2/rgbn/.front-tmp.h5.x.tmp").write_bytes(b"partial")  # never counted
    events = missing_stages(store)
    got = sorted((e["type"], e["fragment"], e.get("face"), e["artifact"]["path"]) for e in events)
    assert got == [("fragment.ready", "F1", None, refs["scans_only"].path),
                   ("rgbn.ready", "F2", "front", refs["rgbn_front"].path)]
    assert all(e["artifact"]["sha256"] == store.ref(e["artifact"]["path"]).sha256 for e in events)


def _tessera(st, *args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())", *args,
                           "--config", str(st.config_path)], capture_output=True, text=True, timeout=60, cwd=REPO)


def test_reconcile_command_queues_missing_stages_and_status_shows_them(make_station):
    st = make_station(routing={"fragment.ready": ["solver"], "rgbn.ready": ["features", "renderer"]})
    _storage(Store(st.root / "storage"))
    st.broker()
    dry = _tessera(st, "reconcile", "--dry-run")
    assert dry.returncode == 0 and "2 event(s) would be queued" in dry.stdout
    with st.subscriber(0) as sub:
        assert sub.next(0.3) is None, "a dry run queues nothing"
        run = _tessera(st, "reconcile")
        assert run.returncode == 0, run.stdout + run.stderr
        events = collect(sub, lambda ev: len(ev) == 2, 10, "two reconciled events")
    assert {(e["type"], e["fragment"]) for _, e in events} == {("fragment.ready", "F1"), ("rgbn.ready", "F2")}
    status = _tessera(st, "status")
    assert status.returncode == 0
    assert "solver=1" in status.stdout and "features=1" in status.stdout and "renderer=1" in status.stdout
    down = _tessera(st, "status", "--set", f"broker.port={free_port()}", "--set", "client.timeout_s=0.2",
                    "--set", "client.retries=1")
    assert down.returncode == 1 and "did not answer" in down.stdout
