"""Artifact store: atomic immutable writes, digest/size checks, schema, provenance, spool import."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from common.store import (ArtifactError, ArtifactRef, Store, StorageError, StorageFull, StorageReadOnly,
                          StorageUnavailable, content_key)


def _fill(f):
    f.create_dataset("x", data=np.arange(100, dtype=np.float32))


def test_write_is_atomic_and_carries_schema_and_provenance(tmp_path):
    store = Store(tmp_path)
    ref = store.write("fragments/F1/rgbn/front-abc.h5", "tessera.test", 3, _fill, provenance={"inputs": ["d1"]})
    path = tmp_path / "fragments/F1/rgbn/front-abc.h5"
    assert ref.bytes == path.stat().st_size
    assert ref.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    assert [p.name for p in path.parent.iterdir()] == [path.name], "no temporary file left behind"
    with store.open(ref, schema="tessera.test") as f:
        assert f.attrs["schema_version"] == 3
        assert json.loads(f.attrs["provenance"]) == {"inputs": ["d1"]}
        assert np.array_equal(f["x"][()], np.arange(100))


def test_existing_artifact_is_immutable_and_rewrite_returns_same_ref(tmp_path):
    store = Store(tmp_path)
    a = store.write("a.h5", "s", 1, _fill)
    b = store.write("a.h5", "s", 1, lambda f: f.create_dataset("y", data=[1]))
    assert a == b
    with store.open(b) as f:
        assert "y" not in f


def test_failed_fill_leaves_nothing(tmp_path):
    store = Store(tmp_path)

    def boom(f):
        raise RuntimeError("disk full")
    with pytest.raises(RuntimeError):
        store.write("d/b.h5", "s", 1, boom)
    assert not (tmp_path / "d").exists() or list((tmp_path / "d").iterdir()) == []


def test_digest_size_truncation_and_schema_are_checked_on_read(tmp_path):
    store = Store(tmp_path)
    ref = store.write("a.h5", "s", 1, _fill)
    with pytest.raises(ArtifactError, match="sha256"):
        with store.open(ArtifactRef(ref.path, "0" * 64, ref.bytes)):
            pass
    with pytest.raises(ArtifactError, match="bytes"):
        with store.open(ArtifactRef(ref.path, ref.sha256, ref.bytes + 1)):
            pass
    with pytest.raises(ArtifactError, match="schema"):
        with store.open(ref, schema="other"):
            pass
    with pytest.raises(ArtifactError, match="schema version 1; this reader understands up to 0"):
        with store.open(ref, schema="s", version=0):
            pass
    with store.open(ref, schema="s", version=2):  # older files stay readable
        pass
    with open(tmp_path / "a.h5", "r+b") as fh:
        fh.truncate(ref.bytes // 3)
    with pytest.raises(ArtifactError, match="not a readable HDF5"):
        with store.open(store.ref("a.h5")):
            pass


@pytest.mark.parametrize("bad", ["/etc/passwd", "../x.h5", "a/../../x.h5", ""])
def test_paths_cannot_escape_the_root(tmp_path, bad):
    with pytest.raises(ArtifactError):
        Store(tmp_path).path(bad)


def test_content_key_depends_on_every_part():
    k = content_key("sha-a", "solver", "1")
    assert k == content_key("sha-a", "solver", "1")
    assert len({k, content_key("sha-b", "solver", "1"), content_key("sha-a", "solver", "2"),
                content_key("sha-a", "solver1", "")}) == 4


def test_missing_mount_is_unavailable_and_never_created(tmp_path):
    store = Store(tmp_path / "mnt", create=False)
    assert not store.available() and not (tmp_path / "mnt").exists()
    with pytest.raises(StorageUnavailable, match="not reachable"):
        store.write("fragments/F/rgbn/front-1.h5", "s", 1, _fill)
    with pytest.raises(OSError):  # the scanner falls back to its spool on OSError
        store.write("fragments/F/rgbn/front-1.h5", "s", 1, _fill)
    assert not (tmp_path / "mnt").exists(), "a missing mount is not replaced by local directories"
    (tmp_path / "mnt").mkdir()
    assert store.available() and store.write("a.h5", "s", 1, _fill).bytes > 0


def test_import_file_copies_verified_and_refuses_wrong_digest(tmp_path):
    spool, lab = Store(tmp_path / "spool"), Store(tmp_path / "lab")
    ref = spool.write("fragments/F/scans/s.h5", "s", 1, _fill)
    with pytest.raises(ArtifactError, match="not copied"):
        lab.import_file(spool.path(ref.path), ref.path, "f" * 64)
    assert not lab.exists(ref.path) and not any(p.is_file() for p in (tmp_path / "lab").rglob("*"))
    assert lab.import_file(spool.path(ref.path), ref.path, ref.sha256) == ref
    assert lab.import_file(spool.path(ref.path), ref.path, ref.sha256) == ref  # idempotent


def test_works_with_hdf5_file_locking_off_while_another_reader_holds_the_file(tmp_path):
    store = Store(tmp_path, file_locking=False)
    ref = store.write("a.h5", "s", 1, _fill)
    with store.open(ref) as f1, store.open(ref) as f2:
        assert f1["x"].shape == f2["x"].shape


def test_sweep_removes_only_stale_temporary_files_of_dead_writers(tmp_path):
    import os
    import time
    store = Store(tmp_path)
    ref = store.write("fragments/F1/rgbn/front-a.h5", "tessera.test", 1, lambda f: f.create_dataset("x", data=[1]))
    folder = tmp_path / "fragments" / "F1" / "rgbn"
    stale = folder / ".front-b.h5.abc123.tmp"
    fresh = folder / ".front-c.h5.def456.tmp"
    stale.write_bytes(b"half an HDF5 file")
    fresh.write_bytes(b"a write in progress")
    old = time.time() - 7200
    os.utime(stale, (old, old))
    assert store.sweep_temporary(older_than_s=3600) == ["fragments/F1/rgbn/.front-b.h5.abc123.tmp"]
    assert not stale.exists() and fresh.exists()
    assert store.ref(ref.path) == ref  # finished artifacts are untouched


def test_temporary_name_carries_host_and_pid_of_the_writer(tmp_path):
    from common.store import _TEMP_NAME, _host_label
    import common.store as cs
    seen = []
    store = Store(tmp_path)
    real = cs._write_bytes

    def spy(path, data):
        seen.extend(p.name for p in (tmp_path / "d").iterdir())
        real(path, data)
    cs._write_bytes = spy
    try:
        store.write("d/front-a.h5", "s", 1, _fill)
    finally:
        cs._write_bytes = real
    m = _TEMP_NAME.match(seen[0])
    assert m and m["final"] == "front-a.h5" and m["host"] == _host_label() and int(m["pid"]) == __import__("os").getpid()


_WRITER = """
import sys, time
sys.path.insert(0, {repo!r})
import common.store as cs
def stalled_write(path, data):  # the file is built in memory; the process dies while writing it out
    with open(path, "wb") as fh:
        fh.write(bytes(data[:10]))
        fh.flush()
    print("writing", flush=True)
    time.sleep(600)
cs._write_bytes = stalled_write
cs.Store({root!r}).write("fragments/F1/rgbn/front-k.h5", "tessera.test", 1, lambda f: f.create_dataset("x", data=[1, 2, 3]))
"""


def test_sweep_removes_at_once_the_temporary_file_of_a_writer_killed_mid_write(tmp_path):
    import signal
    import subprocess
    import sys
    from pathlib import Path
    repo = str(Path(__file__).resolve().parents[1])
    proc = subprocess.Popen([sys.executable, "-c", _WRITER.format(repo=repo, root=str(tmp_path))],
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "writing"
        store = Store(tmp_path)
        assert store.sweep_temporary() == [], "a live writer's file is kept"
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        left = [p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob(".*.tmp")]
        assert len(left) == 1, "SIGKILL mid-write leaves the temporary file"
        assert store.sweep_temporary() == left  # fresh, but its writer is dead
        assert not list(tmp_path.rglob(".*.tmp")) and not store.exists("fragments/F1/rgbn/front-k.h5")
    finally:
        proc.kill()
        proc.wait(10)


def test_sweep_keeps_fresh_files_of_other_hosts_and_live_writers_and_spots_reused_pids(tmp_path):
    import os
    import subprocess
    import sys
    import time
    from common.store import _host_label
    store = Store(tmp_path)
    host = _host_label()
    live = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        time.sleep(0.3)
        folder = tmp_path / "fragments" / "F1" / "rgbn"
        folder.mkdir(parents=True)
        names = {
            "mine": f".front-a.h5.{host}.{os.getpid()}.abc_123.tmp",        # this process: alive
            "live": f".front-b.h5.{host}.{live.pid}.def456.tmp",             # another live process
            "reused": f".front-c.h5.{host}.{live.pid}.ghi789.tmp",           # pid now of a newer process
            "other_host": f".front-d.h5.{host}x.999999.jkl012.tmp",          # can't tell from here: age rule
            "old_other_host": f".front-e.h5.{host}x.999999.mno345.tmp",
            "old_format": ".front-f.h5.pqr678.tmp",
        }
        for n in names.values():
            (folder / n).write_bytes(b"partial")
        before_live = time.time() - 600  # written 10 min ago, before the live process started
        os.utime(folder / names["reused"], (before_live, before_live))
        ancient = time.time() - 7200
        os.utime(folder / names["old_other_host"], (ancient, ancient))
        removed = {p.rsplit("/", 1)[1] for p in store.sweep_temporary(older_than_s=3600)}
        assert removed == {names["reused"], names["old_other_host"]}
        assert {p.name for p in folder.iterdir()} == set(names.values()) - removed
    finally:
        live.kill()
        live.wait(10)


# -- full and read-only storage (issue 19: libhdf5 crashed the process with SIGSEGV on ENOSPC) -------

@pytest.fixture
def tiny_mount(tmp_path):
    """A 2 MB tmpfs mounted at a fresh directory (needs root; skipped, saying why, otherwise)."""
    import os
    import subprocess
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    if os.geteuid() != 0:
        pytest.skip("mounting a tiny tmpfs needs root")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def _big_fill(nbytes):
    def fill(f):  # incompressible: the file really is this large
        f.create_dataset("x", data=np.random.default_rng(0).integers(0, 255, nbytes, dtype=np.uint8))
    return fill


_FULL_WRITER = """
import sys
sys.path.insert(0, {repo!r})
import numpy as np
import common.store as cs
if {skip_check}:
    cs.check_free_space = lambda *a: None   # reach the write itself: ENOSPC from the kernel
store = cs.Store({root!r})
data = np.random.default_rng(0).integers(0, 255, 3_000_000, dtype=np.uint8)
try:
    store.write("fragments/F1/scans/scans-k.h5", "tessera.test", 1, lambda f: f.create_dataset("x", data=data))
except cs.StorageFull as exc:
    print("StorageFull:", exc)
    sys.exit(3)
print("written?")
"""


@pytest.mark.parametrize("skip_check", [False, True], ids=["free-space-check", "enospc-while-writing"])
def test_full_disk_raises_storage_full_and_the_process_survives(tiny_mount, skip_check):
    import subprocess
    import sys
    from pathlib import Path
    repo = str(Path(__file__).resolve().parents[1])
    r = subprocess.run([sys.executable, "-c", _FULL_WRITER.format(repo=repo, root=str(tiny_mount), skip_check=skip_check)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 3, f"exit {r.returncode} (139 = the segfault of issue 19): {r.stdout}{r.stderr}"
    assert "storage full" in r.stdout
    assert not [p for p in tiny_mount.rglob("*") if p.is_file()], "nothing half-written left behind"


def test_full_disk_check_names_the_artifact_and_sizes(tiny_mount):
    store = Store(tiny_mount)
    with pytest.raises(StorageFull, match=r"fragments/F1/rgbn/front-k.h5 needs \d+ bytes, \d+ free"):
        store.write("fragments/F1/rgbn/front-k.h5", "tessera.test", 1, _big_fill(3_000_000))
    small = store.write("fragments/F1/rgbn/front-s.h5", "tessera.test", 1, _fill)  # still usable for what fits
    assert store.ref(small.path) == small


def test_read_only_storage_raises_storage_read_only(tiny_mount):
    import subprocess
    store = Store(tiny_mount)
    store.write("fragments/F1/rgbn/front-a.h5", "tessera.test", 1, _fill)
    subprocess.run(["mount", "-o", "remount,ro", str(tiny_mount)], check=True)
    with pytest.raises(StorageReadOnly, match="read-only"):
        store.write("fragments/F1/rgbn/front-b.h5", "tessera.test", 1, _fill)
    with pytest.raises(StorageReadOnly):
        store.write("fragments/F2/rgbn/front-b.h5", "tessera.test", 1, _fill)  # a folder to create
    assert isinstance(StorageReadOnly(), StorageError) and isinstance(StorageFull(), OSError)
    with store.open("fragments/F1/rgbn/front-a.h5") as f:  # reading still works
        assert f["x"].shape == (100,)


def test_storage_errors_read_as_their_message_without_the_errno_prefix():
    """OSError's str() puts ``[Errno 28]`` before the message: the export's and reconstruct's stderr said
    ``... [Errno 28] storage full: ...`` where the docs quote ``...: storage full: ...``."""
    import errno
    assert str(StorageFull(errno.ENOSPC, "storage full: x")) == "storage full: x"
    assert str(StorageReadOnly(errno.EROFS, "storage read-only: y")) == "storage read-only: y"
    exc = StorageFull(errno.ENOSPC, "storage full: x")
    assert exc.errno == errno.ENOSPC and exc.strerror == "storage full: x"     # still an OSError with its errno
    assert str(StorageFull("bare")) == "bare" and str(StorageFull()) == ""     # no strerror: OSError's own


def test_import_file_on_full_disk_raises_storage_full_and_leaves_nothing(tiny_mount, tmp_path):
    src = Store(tmp_path / "spool")
    ref = src.write("fragments/F1/scans/scans-k.h5", "tessera.test", 1, _big_fill(3_000_000))
    dst = Store(tiny_mount)
    with pytest.raises(StorageFull):
        dst.import_file(src.path(ref.path), ref.path, ref.sha256)
    assert not [p for p in tiny_mount.rglob("*") if p.is_file()]


def test_write_returns_the_digest_of_the_bytes_on_disk(tmp_path):
    store = Store(tmp_path)
    ref = store.write("a.h5", "s", 1, _big_fill(50_000))
    assert ref == ArtifactRef("a.h5", hashlib.sha256((tmp_path / "a.h5").read_bytes()).hexdigest(),
                              (tmp_path / "a.h5").stat().st_size)


# -- racing writers of one content key (a job re-dispatched while its first worker still runs) --------

def _no_hard_links(monkeypatch):
    """The file system refuses hard links (FAT, some SMB mounts): link(2) fails with EPERM."""
    import errno
    import os

    def link(src, dst, **kw):
        raise OSError(errno.EPERM, os.strerror(errno.EPERM), str(src))
    monkeypatch.setattr(os, "link", link)


def _race_into(monkeypatch, hook_name, first_writer):
    """Run ``first_writer`` while the writer under test is past its exists() check (inside ``hook_name``)."""
    import common.store as cs
    real, done = getattr(cs, hook_name), {}

    def racing(*args):
        monkeypatch.setattr(cs, hook_name, real)
        done["ref"] = first_writer()
        return real(*args)
    monkeypatch.setattr(cs, hook_name, racing)
    return done


@pytest.mark.parametrize("links", [True, False], ids=["hard-links", "no-hard-links"])
def test_racing_writers_of_one_key_keep_the_first_artifact(tmp_path, monkeypatch, links):
    """docs/storage.md: an existing path is never rewritten. The second writer's bytes differ
    (``created``); the announced pointer of the first must still verify."""
    if not links:
        _no_hard_links(monkeypatch)
    store = Store(tmp_path)
    first = _race_into(monkeypatch, "_write_bytes", lambda: store.write("d/a.h5", "s", 1, _fill))
    second = store.write("d/a.h5", "s", 1, lambda f: f.create_dataset("y", data=[1]))
    assert second == first["ref"], "the later writer returns the pointer of the bytes really there"
    assert hashlib.sha256((tmp_path / "d/a.h5").read_bytes()).hexdigest() == first["ref"].sha256
    with store.open(first["ref"]) as f:
        assert "x" in f and "y" not in f
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["a.h5"], "no temporary file left behind"


def test_write_without_hard_links_and_overwrite_still_work(tmp_path, monkeypatch):
    _no_hard_links(monkeypatch)
    store = Store(tmp_path)
    ref = store.write("models/m.h5", "s", 1, _fill)
    assert store.ref(ref.path) == ref
    new = store.write("models/m.h5", "s", 1, lambda f: f.create_dataset("y", data=[1]), overwrite=True)
    assert new != ref and store.ref(new.path) == new, "overwrite=True (models) still replaces"


def test_import_file_never_replaces_an_artifact_of_another_digest(tmp_path):
    """The spool's copy disagrees with what storage holds: storage keeps its file, and the caller
    (whose event announces the spool's digest) hears both digests instead of a silent swap."""
    spool, lab = Store(tmp_path / "spool"), Store(tmp_path / "lab")
    there = lab.write("fragments/F/scans/s.h5", "s", 1, _fill)
    ref = spool.write("fragments/F/scans/s.h5", "s", 1, lambda f: f.create_dataset("y", data=[1]))
    with pytest.raises(ArtifactError, match=f"{there.sha256[:12]}.*{ref.sha256[:12]}"):
        lab.import_file(spool.path(ref.path), ref.path, ref.sha256)
    assert lab.ref(there.path) == there, "the existing artifact is kept, bytes unchanged"
    assert [p.name for p in (tmp_path / "lab/fragments/F/scans").iterdir()] == ["s.h5"]


def test_import_file_racing_another_writer_keeps_its_file(tmp_path, monkeypatch):
    spool, lab = Store(tmp_path / "spool"), Store(tmp_path / "lab")
    ref = spool.write("fragments/F/scans/s.h5", "s", 1, lambda f: f.create_dataset("y", data=[1]))
    other = _race_into(monkeypatch, "check_free_space", lambda: lab.write(ref.path, "s", 1, _fill))
    with pytest.raises(ArtifactError, match="sha256"):
        lab.import_file(spool.path(ref.path), ref.path, ref.sha256)
    assert lab.ref(ref.path) == other["ref"]
    assert [p.name for p in (tmp_path / "lab/fragments/F/scans").iterdir()] == ["s.h5"]


def test_sweep_removes_the_folder_an_interrupted_export_left_once_it_is_old(tmp_path):
    """An export writes into ``.<id>.<random>.tmp`` beside its final folder; one killed midway left it for good
    (the sweep looked at files only). A stale one goes; a fresh one, perhaps an export running now, stays."""
    import os
    import time

    store = Store(tmp_path)
    stale = store.root / "exports" / ".F1.ab12.tmp"
    fresh = store.root / "exports" / ".F2.cd34.tmp"
    for d in (stale, fresh):
        d.mkdir(parents=True)
        (d / "front-albedo.png").write_bytes(b"png")
    old = time.time() - 7200
    os.utime(stale, (old, old))
    removed = store.sweep_temporary(older_than_s=3600)
    assert removed == ["exports/.F1.ab12.tmp"] and not stale.exists() and (fresh / "front-albedo.png").is_file()
