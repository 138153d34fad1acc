"""``tessera import images``: pictures -> colour-only RGBN faces, manifests, resumable, the bus path."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

from common.bus.outbox import Outbox
from common.rgbn.image import load_rgbn
from common.store import Store
from services.cli import main
from tests.bus.conftest import collect, make_station, wait_for  # noqa: F401  (fixture)

REPO = Path(__file__).resolve().parents[2]


def _blob(h, w, seed):
    """Ground-truth mask: an ellipse with a notch, placed away from the border."""
    rng = np.random.default_rng(seed)
    m = np.zeros((h, w), np.uint8)
    cv2.ellipse(m, (w // 2, h // 2), (int(w * rng.uniform(0.2, 0.3)), int(h * rng.uniform(0.2, 0.3))),
                float(rng.uniform(0, 180)), 0, 360, 1, -1)
    cv2.circle(m, (w // 2 + w // 5, h // 2), h // 10, 0, -1)
    return m > 0


def _picture(path, seed=0, h=240, w=320, alpha=False, bits=8):
    truth = _blob(h, w, seed)
    rng = np.random.default_rng(seed)
    paint = np.array([180, 120, 70]) + rng.normal(0, 8, (h, w, 3))
    paint[:, w // 2: w // 2 + 20] = (90, 30, 30)
    if alpha:
        img = np.dstack([np.where(truth[..., None], paint, 0), truth * 255.0])
    else:
        img = np.where(truth[..., None], paint, np.array([235, 235, 230]) + rng.normal(0, 2, (h, w, 3)))
    img = np.clip(img, 0, 255)
    if bits == 16:
        img = (img * 257).astype(np.uint16)
    else:
        img = img.astype(np.uint8)
    bgr = img[..., [2, 1, 0, 3]] if alpha else img[..., ::-1]
    assert cv2.imwrite(str(path), bgr)
    return truth


def _rgbn_files(root):
    return sorted((Path(root) / "fragments").rglob("*.h5"))


def test_alpha_and_plain_pictures_become_rgbn_faces_with_the_true_mask(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    truths = {"A1": _picture(src / "A1.png", 1, alpha=True), "B2": _picture(src / "B2.png", 2),
              "C3": _picture(src / "C3.tif", 3, bits=16)}
    assert main(["import", "images", str(src), "--dpi", "300", "--store", str(tmp_path / "st")]) == 0
    store = Store(tmp_path / "st")
    files = _rgbn_files(tmp_path / "st")
    assert [f.parts[-3] for f in files] == ["A1", "B2", "C3"]
    for f in files:
        img = load_rgbn(store, f.relative_to(tmp_path / "st").as_posix())
        truth = truths[f.parts[-3]]
        # the face is the piece and 2 mm round it (24 px at 300 dpi), cut where the picture allows
        (x0, y0), (h, w) = img.attrs["crop_px"], img.mask.shape
        rows, cols = np.flatnonzero(truth.any(axis=1)), np.flatnonzero(truth.any(axis=0))
        corners = (y0, x0, y0 + h, x0 + w)
        want = (max(rows[0] - 24, 0), max(cols[0] - 24, 0), min(rows[-1] + 25, truth.shape[0]),
                min(cols[-1] + 25, truth.shape[1]))
        assert np.abs(np.subtract(corners, want)).max() <= 2, (corners, want)   # the mask's edge within 2 px
        window = truth[y0:y0 + h, x0:x0 + w]
        iou = (img.mask & window).sum() / (img.mask | window).sum()
        assert iou > 0.98, (f, iou)
        assert img.dpi == 300 and img.normals is None


def test_manifest_metadata_is_kept_with_the_fragment(tmp_path, capsys):
    _picture(tmp_path / "p1.jpg", 4)
    _picture(tmp_path / "p2.png", 5, alpha=True)
    (tmp_path / "finds.csv").write_text(
        "File;Inventory number;Find-spot;Context;Date;Notes;dpi;Conservator\n"
        "p1.jpg;Inv. 1998/12;Room 4, north wall;US 102;1998-05-02;red band, burnt edge;150;M. Rossi\n"
        "p2.png;Inv. 1998/13;Room 4;US 103;1998-05-03;;600;\n", encoding="utf-8")
    assert main(["import", "images", "--manifest", str(tmp_path / "finds.csv"), "--store", str(tmp_path / "st")]) == 0
    store = Store(tmp_path / "st")
    files = {f.parts[-3]: f for f in _rgbn_files(tmp_path / "st")}
    assert sorted(files) == ["Inv.-1998-12", "Inv.-1998-13"]
    img = load_rgbn(store, files["Inv.-1998-12"].relative_to(tmp_path / "st").as_posix())
    meta = json.loads(img.attrs["metadata"])
    assert meta == {"inventory": "Inv. 1998/12", "find_spot": "Room 4, north wall", "context": "US 102",
                    "date": "1998-05-02", "notes": "red band, burnt edge", "conservator": "M. Rossi",
                    "source_file": "p1.jpg"}
    assert img.dpi == 150
    assert load_rgbn(store, files["Inv.-1998-13"].relative_to(tmp_path / "st").as_posix()).dpi == 600


def test_bad_pictures_are_refused_by_name_and_nothing_is_written_for_them(tmp_path, capsys):
    src = tmp_path / "in"
    src.mkdir()
    _picture(src / "good.png", 6)
    cv2.imwrite(str(src / "blank.png"), np.full((100, 100, 3), 200, np.uint8))
    _picture(src / "cut.png", 7)
    data = (src / "cut.png").read_bytes()
    (src / "cut.png").write_bytes(data[: len(data) // 2])
    noise = np.random.default_rng(0).integers(0, 4, (200, 300, 3)).astype(np.uint8)
    plain = np.full((200, 300, 3), 230, np.uint8) + noise
    cv2.imwrite(str(src / "nothing.png"), plain)
    assert main(["import", "images", str(src), "--dpi", "300", "--store", str(tmp_path / "st")]) == 1
    captured = capsys.readouterr()
    assert "imported 1, already imported 0, refused 3" in captured.out   # the summary, on (today's) stdout
    err = captured.err
    assert "refused blank.png:" in err and "is blank" in err
    assert "refused cut.png:" in err and "truncated" in err
    assert "refused nothing.png:" in err and "no fragment found" in err
    assert [f.parts[-3] for f in _rgbn_files(tmp_path / "st")] == ["good"]
    assert not list((tmp_path / "st").rglob("*.tmp"))


def test_missing_dpi_and_duplicate_ids_stop_before_anything_is_imported(tmp_path, capsys):
    _picture(tmp_path / "a.png", 1)
    assert main(["import", "images", str(tmp_path / "a.png"), "--store", str(tmp_path / "st")]) == 2
    assert "no dpi" in capsys.readouterr().err
    (tmp_path / "b").mkdir()
    _picture(tmp_path / "b" / "a.png", 2)
    assert main(["import", "images", str(tmp_path / "a.png"), str(tmp_path / "b" / "a.png"), "--dpi", "300",
                 "--store", str(tmp_path / "st")]) == 2
    assert "fragment a (front) is also given by" in capsys.readouterr().err
    assert not (tmp_path / "st" / "fragments").exists()


def test_the_same_picture_under_a_second_id_is_refused_naming_the_first(tmp_path, capsys):
    """The RePAIR trial: a picture imported once with a manifest's inventory number and once by its file name
    became two fragments, which the matcher proposed as a join near the top of its queue. The second import (or a
    copy of the file under another name, in the same run or a later one) is refused naming the fragment it already
    is; ``--allow-duplicates`` imports it anyway."""
    store = tmp_path / "st"
    _picture(tmp_path / "RPf_00123.png", 4, alpha=True)
    (tmp_path / "finds.csv").write_text("file,inventory,dpi\nRPf_00123.png,Inv. 1998/12,187.2\n", encoding="utf-8")
    assert main(["import", "images", "--manifest", str(tmp_path / "finds.csv"), "--store", str(store)]) == 0
    capsys.readouterr()
    (tmp_path / "copies").mkdir()
    (tmp_path / "copies" / "copy_of_123.png").write_bytes((tmp_path / "RPf_00123.png").read_bytes())
    assert main(["import", "images", str(tmp_path / "RPf_00123.png"), str(tmp_path / "copies"), "--dpi", "187.2",
                 "--store", str(store)]) == 1
    out = capsys.readouterr()
    assert "imported 0, already imported 0, refused 2" in out.out
    for name, fid in (("RPf_00123.png", "RPf_00123"), ("copy_of_123.png", "copy_of_123")):
        assert (f"refused {name}: the same file (sha256 " in out.err and
                f"is already imported as fragment Inv.-1998-12 (front, 187.2 dpi: fragments/Inv.-1998-12/rgbn/front-"
                in out.err and f"not imported again as {fid} (front): give --allow-duplicates" in out.err), out.err
    assert sorted(f.parts[-3] for f in _rgbn_files(store)) == ["Inv.-1998-12"]
    # the same picture, twice in one run: the second copy is refused
    (tmp_path / "two").mkdir()
    _picture(tmp_path / "two" / "A.png", 5)
    (tmp_path / "two" / "B.png").write_bytes((tmp_path / "two" / "A.png").read_bytes())
    assert main(["import", "images", str(tmp_path / "two"), "--dpi", "300", "--store", str(store)]) == 1
    err = capsys.readouterr().err
    assert "refused B.png: the same file" in err and "already imported as fragment A (front, 300 dpi" in err
    # asked for, it goes in; the first import run again is already imported, not refused
    assert main(["import", "images", str(tmp_path / "RPf_00123.png"), "--dpi", "187.2", "--allow-duplicates",
                 "--store", str(store)]) == 0
    assert sorted(f.parts[-3] for f in _rgbn_files(store)) == ["A", "Inv.-1998-12", "RPf_00123"]
    assert main(["import", "images", "--manifest", str(tmp_path / "finds.csv"), "--store", str(store)]) == 0
    assert "imported 0, already imported 1, refused 0" in capsys.readouterr().out


def test_the_same_picture_at_another_dpi_is_refused_naming_both_unless_replace(tmp_path, capsys):
    """Re-importing a picture for the same fragment at another dpi silently added a second, rescaled face: it is
    refused naming both dpi values; ``--replace`` imports it, the new face the one every stage and page uses."""
    from common.imports.export import latest_faces

    store = tmp_path / "st"
    _picture(tmp_path / "F7.png", 6)
    assert main(["import", "images", str(tmp_path / "F7.png"), "--dpi", "300", "--store", str(store)]) == 0
    capsys.readouterr()
    assert main(["import", "images", str(tmp_path / "F7.png"), "--dpi", "150", "--store", str(store)]) == 1
    err = capsys.readouterr().err
    assert ("refused F7.png: the same file is already imported for fragment F7 (front) at 300 dpi; this import gives "
            "150 dpi: give --replace") in err
    assert len(_rgbn_files(store)) == 1
    # the same dpi with other metadata is no rescaled copy: imported as before (the newest face is used)
    (tmp_path / "m.csv").write_text("file,inventory,notes\nF7.png,F7,burnt edge\n", encoding="utf-8")
    assert main(["import", "images", "--manifest", str(tmp_path / "m.csv"), "--dpi", "300", "--store", str(store)]) == 0
    assert main(["import", "images", str(tmp_path / "F7.png"), "--dpi", "150", "--replace", "--store", str(store)]) == 0
    assert len(_rgbn_files(store)) == 3
    newest = latest_faces(Store(store), "F7")["front"]
    assert load_rgbn(Store(store), newest).dpi == 150
    # replaced, its metadata corrected at the dpi it has now: no rescale, not refused
    assert main(["import", "images", "--manifest", str(tmp_path / "m.csv"), "--dpi", "150", "--store", str(store)]) == 0


def test_a_picture_imported_from_another_ledger_is_found_on_storage(tmp_path, capsys, monkeypatch):
    """What another bench (another ledger) or an older ledger imported is read from the artifacts' provenance
    (source_sha256, dpi), once: the next run reads it from ``sources.jsonl`` beside the ledger."""
    import common.imports.sources as sources

    store = tmp_path / "st"
    _picture(tmp_path / "G1.png", 7)
    assert main(["import", "images", str(tmp_path / "G1.png"), "--dpi", "300", "--store", str(store)]) == 0
    (store / "imports" / "ledger.jsonl").unlink()   # as if imported by another bench
    (tmp_path / "renamed.png").write_bytes((tmp_path / "G1.png").read_bytes())
    opened = []
    real = sources._provenance_sources
    monkeypatch.setattr(sources, "_provenance_sources", lambda path, rel: opened.append(rel) or real(path, rel))
    for _ in range(2):
        assert main(["import", "images", str(tmp_path / "renamed.png"), "--dpi", "300", "--store", str(store)]) == 1
        assert "is already imported as fragment G1 (front, 300 dpi" in capsys.readouterr().err
    assert len(opened) == 1 and opened[0].startswith("fragments/G1/rgbn/front-")   # read once, then from the cache
    assert json.loads((store / "imports" / "sources.jsonl").read_text())["dpi"] == 300


def test_import_killed_half_way_resumes_and_imports_nothing_twice(tmp_path):
    src = tmp_path / "in"
    src.mkdir()
    n = 8
    for i in range(n):
        _picture(src / f"F{i:02d}.png", i, h=900, w=1200)
    store = tmp_path / "st"
    ledger = store / "imports" / "ledger.jsonl"
    cmd = [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
           "import", "images", str(src), "--dpi", "300", "--store", str(store)]
    env = dict(os.environ, PYTHONPATH=str(REPO))
    p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for(lambda: ledger.is_file() and len(ledger.read_text().splitlines()) >= 2, 120, "two pictures imported")
    p.send_signal(signal.SIGKILL)
    p.wait(10)
    done_first = len(ledger.read_text().splitlines())
    assert done_first < n, "the import was killed half-way"
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert f"imported {n - done_first}, already imported {done_first}" in out.stdout
    keys = [json.loads(line)["key"] for line in ledger.read_text().splitlines()]
    assert len(keys) == n and len(set(keys)) == n
    files = _rgbn_files(store)
    assert sorted(f.parts[-3] for f in files) == [f"F{i:02d}" for i in range(n)]   # one face each, none twice
    for f in files:   # every artifact complete (a write cut by the kill never reached its final name)
        assert load_rgbn(Store(store), f.relative_to(store).as_posix()).mask.any()


def test_with_the_broker_down_events_wait_in_the_outbox_then_go_out(make_station, tmp_path):
    st = make_station(routing={"rgbn.ready": ["noop"], "noop.job": ["noop"]})
    src = tmp_path / "in"
    src.mkdir()
    for i in range(3):
        _picture(src / f"P{i}.png", 10 + i)
    args = ["import", "images", str(src), "--dpi", "200", "--config", str(st.config_path), "--wait", "0"]
    assert main(args) == 0          # imported: artifacts on storage, events safe in the outbox
    box = Outbox(st.root / "bench")
    pending = [e for _, e, _ in box.pending()]
    box.close()
    assert [e["type"] for e in pending] == ["rgbn.ready"] * 3
    assert [e["fragment"] for e in pending] == ["P0", "P1", "P2"]
    storage = Store(st.root / "storage")
    for e in pending:
        with storage.open(e["artifact"], schema="tessera.rgbn") as f:
            assert f.attrs["face"] == "front"
    assert main(args) == 0          # a second run imports nothing and queues nothing twice
    box = Outbox(st.root / "bench")
    assert len(box) == 3
    box.close()
    st.broker()
    with st.subscriber(0) as sub:
        assert main(args[:-1] + ["20"]) == 0     # the next run drains the outbox
        events = collect(sub, lambda ev: sum(e["type"] == "rgbn.ready" for _, e in ev) == 3, 30, "3 rgbn.ready")
    assert sorted(e["fragment"] for _, e in events if e["type"] == "rgbn.ready") == ["P0", "P1", "P2"]
    box = Outbox(st.root / "bench")
    assert len(box) == 0
    box.close()


def test_with_storage_unreachable_artifacts_go_to_the_spool(make_station, tmp_path):
    st = make_station()
    _picture(tmp_path / "S1.png", 20)
    missing = tmp_path / "nfs-not-mounted"
    assert main(["import", "images", str(tmp_path / "S1.png"), "--dpi", "200", "--config", str(st.config_path),
                 "--set", f'storage.root="{missing}"', "--set", "storage.create_root=false", "--wait", "0"]) == 0
    assert not missing.exists()
    box = Outbox(st.root / "bench")
    (_, event, spooled), = box.pending()
    assert spooled == event["artifact"]["path"] and box.spool.exists(spooled)
    box.close()


def test_pictures_show_each_mask_and_a_file_in_their_place_is_refused(tmp_path, capsys):
    truth = _picture(tmp_path / "M1.png", 30)
    pics = tmp_path / "pics"
    assert main(["import", "images", str(tmp_path / "M1.png"), "--dpi", "300", "--store", str(tmp_path / "st"),
                 "--pictures", str(pics)]) == 0
    pic = cv2.imread(str(pics / "M1-front.png"))[..., ::-1]
    (rgbn,) = _rgbn_files(tmp_path / "st")
    x0, y0 = load_rgbn(Store(tmp_path / "st"), rgbn.relative_to(tmp_path / "st").as_posix()).attrs["crop_px"]
    truth = truth[y0:y0 + pic.shape[0], x0:x0 + pic.shape[1]]   # the picture shows the face: the piece, cut out
    assert pic.shape[:2] == truth.shape and truth.any()
    outline = (pic[..., 0] == 255) & (pic[..., 1] == 0) & (pic[..., 2] == 255)
    edge = truth ^ cv2.erode(truth.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    near = cv2.dilate(outline.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert near[edge].mean() > 0.95                   # the magenta outline follows the true edge (1 px)
    assert edge[outline].mean() > 0.9
    (tmp_path / "afile").write_text("x")
    assert main(["import", "images", str(tmp_path / "M1.png"), "--dpi", "300", "--store", str(tmp_path / "st2"),
                 "--pictures", str(tmp_path / "afile")]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    assert not (tmp_path / "st2").exists()


def test_a_piece_too_close_to_its_background_is_imported_with_a_warning(tmp_path, capsys):
    # pale plaster photographed on white paper: the edge cannot be placed at half coverage, so the
    # import says so, naming the fragment and the share, and still imports it
    src = tmp_path / "in"
    src.mkdir()
    truth = _blob(240, 320, 4)
    rng = np.random.default_rng(4)
    pale = np.where(truth[..., None], np.array([226, 224, 218]), np.array([240, 238, 232])) + rng.normal(0, 1, (240, 320, 3))
    assert cv2.imwrite(str(src / "pale.png"), np.clip(pale, 0, 255).astype(np.uint8)[..., ::-1])
    _picture(src / "painted.png", 5)      # ochre on off-white: its edge is placed
    assert main(["import", "images", str(src), "--dpi", "300", "--store", str(tmp_path / "st")]) == 0
    err = capsys.readouterr().err
    assert "warning: pale (pale.png): the piece's edge could be placed at half coverage along only" in err
    assert "warning: painted" not in err
    store = Store(tmp_path / "st")
    faces = {f.parts[-3]: load_rgbn(store, f.relative_to(tmp_path / "st").as_posix()) for f in _rgbn_files(tmp_path / "st")}
    assert faces["pale"].attrs["edge_placed"] < 0.5 <= faces["painted"].attrs["edge_placed"]


def test_a_folder_whose_pictures_are_in_subfolders_says_so_and_names_them(tmp_path, capsys):
    # a lab's collection laid out as RePAIR's: one folder per object, the pictures in those folders
    root = tmp_path / "collection"
    for obj, seed in (("obj_g10", 1), ("obj_g12", 2)):
        (root / obj).mkdir(parents=True)
        _picture(root / obj / f"P{seed}.png", seed, alpha=True)
    (root / "obj_g12" / "truth.csv").write_text("rpf,x,y,rot\n")
    (root / "empty").mkdir()
    assert main(["import", "images", str(root), "--dpi", "150", "--store", str(tmp_path / "st")]) == 2
    err = capsys.readouterr().err
    assert "nothing to import" in err
    assert f"{root} holds no picture itself" in err and "subfolders are not searched" in err
    assert "obj_g10 (1 picture)" in err and "obj_g12 (1 picture)" in err and "empty" not in err
    assert not (tmp_path / "st").exists()
    # naming the subfolders, as the message says, imports them
    assert main(["import", "images", str(root / "obj_g10"), str(root / "obj_g12"), "--dpi", "150",
                 "--store", str(tmp_path / "st")]) == 0
    assert [f.parts[-3] for f in _rgbn_files(tmp_path / "st")] == ["P1", "P2"]
