"""Tests of ``tessera import scans`` (services/cli/import_scans.py) on files written from the simulated flatbed."""

import cv2
import h5py
import numpy as np
import pytest

from common.acquisition.calibration import calibrate_scanner, save_calibration, simulated_target_operator
from common.acquisition.capture import read_scans
from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface
from common.messages import new_message
from common.rgbn.image import load_rgbn
from common.store import Store
from services import solver
from services.cli import main

DPI = 150
AREA = (28.0, 28.0, 72.0, 72.0)


@pytest.fixture(scope="module")
def turned_scans():
    """Four scans of a fragment turned counter-clockwise (as seen on the image), and the simulator."""
    sim = SimulatedFlatbed("files", bed_mm=(100, 100), seed=11)
    sim.place(demo_surface(25, DPI, seed=4), centre_mm=(50, 50))
    scans = []
    for k in range(4):
        if k:
            sim.rotate(-90)
        scans.append(sim.scan(AREA, DPI))
    return sim, scans


def _write(folder, scans, grey=False, eight=False):
    paths = []
    for k, s in enumerate(scans):
        img = (s // 257).astype(np.uint8) if eight else s
        p = folder / f"scan_{k}.png"
        cv2.imwrite(str(p), img.mean(axis=2).astype(img.dtype) if grey else img[..., ::-1])
        paths.append(str(p))
    return paths


def _calibrated_store(root):
    store = Store(root)
    sim = SimulatedFlatbed("files", bed_mm=(120, 120), seed=12)
    save_calibration(store, calibrate_scanner(sim, simulated_target_operator(sim), area_mm=(50, 50, 70, 70)))
    return store


def _scans_files(root):
    return sorted((root / "fragments").rglob("scans-*.h5")) if (root / "fragments").exists() else []


def test_counter_clockwise_scans_are_detected_imported_and_solved(tmp_path, turned_scans):
    sim, scans = turned_scans
    store = _calibrated_store(tmp_path / "store")
    paths = _write(tmp_path, scans)
    assert main(["import", "scans", *paths, "--fragment", "F-imp-1", "--device", "files", "--dpi", str(DPI),
                 "--store", str(tmp_path / "store")]) == 0
    [art] = _scans_files(tmp_path / "store")
    ref = store.ref(str(art.relative_to(tmp_path / "store")))
    cap = read_scans(store, ref)
    assert cap.device == "files" and [s.rotation for s in cap.scans["front"]] == [0, 270, 180, 90]
    with h5py.File(art) as f:
        assert '"turn": {"front": "ccw"}' in f.attrs["provenance"] or "ccw" in str(f.attrs["provenance"])
    # the solver takes it from there, as for a capture at the bench
    events = solver.handle(new_message("fragment.ready", fragment="F-imp-1", artifact=ref), _Ctx(store))
    img = load_rgbn(store, events[0]["artifact"])
    assert img.has_normals and img.mask.sum() > 0.5 * np.pi * (12.5 / 25.4 * DPI) ** 2
    assert (img.normals[img.mask][:, 2] > 0.5).mean() > 0.95
    # the detected rotations are the simulator's
    regs = [r["angle_deg"] for r in load_rgbn(store, events[0]["artifact"]).attrs.get("registration", [])] or None
    true = [(h.poses[0][0] - sim.history[0].poses[0][0]) for h in sim.history]
    with h5py.File(art) as f:
        import json
        measured = json.loads(f.attrs["provenance"])["registration_check"]["front"]["angles_deg"]
    assert np.allclose((np.array(measured) - true + 180) % 360 - 180, 0, atol=0.5), (measured, true, regs)
    # importing again is a no-op (resumable, content-keyed)
    assert main(["import", "scans", *paths, "--fragment", "F-imp-1", "--device", "files", "--dpi", str(DPI),
                 "--store", str(tmp_path / "store")]) == 0
    assert len(_scans_files(tmp_path / "store")) == 1


class _Ctx:
    def __init__(self, store):
        import logging
        self.store, self.config, self.log = store, {}, logging.getLogger("test")

    def progress(self, *a):
        pass


def test_a_wrong_turn_direction_is_refused_with_the_one_to_give(tmp_path, turned_scans, capsys):
    _, scans = turned_scans
    paths = _write(tmp_path, scans)
    assert main(["import", "scans", *paths, "--fragment", "F-imp-2", "--device", "files", "--dpi", str(DPI),
                 "--turn", "cw", "--store", str(tmp_path / "store")]) == 1
    out = capsys.readouterr()
    text = out.out + out.err
    assert "--turn ccw" in text and "counter-clockwise" in text and "rescan this face" not in text
    assert not _scans_files(tmp_path / "store")


def test_grey_eight_bit_files_are_imported_with_three_equal_channels(tmp_path, turned_scans):
    _, scans = turned_scans
    paths = _write(tmp_path, scans, grey=True, eight=True)
    assert main(["import", "scans", *paths, "--fragment", "F-imp-3", "--device", "files", "--dpi", str(DPI),
                 "--turn", "ccw", "--store", str(tmp_path / "store")]) == 0
    [art] = _scans_files(tmp_path / "store")
    with h5py.File(art) as f:
        d = f["front/scan_0"]
        assert d.dtype == np.uint8 and d.shape[2] == 3 and (d[..., 0] == d[..., 2]).all()


def test_jpeg_scans_are_imported_with_a_one_line_warning(tmp_path, turned_scans, capsys):
    # docs/flatbed.md: JPEG is accepted (8-bit, lossy: its blocks add noise to the normals), saying so once
    _, scans = turned_scans
    paths = []
    for k, s in enumerate(scans):
        p = tmp_path / f"scan_{k}.jpg"
        cv2.imwrite(str(p), (s // 257).astype(np.uint8)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        paths.append(str(p))
    assert main(["import", "scans", *paths, "--fragment", "F-jpg", "--device", "files", "--dpi", str(DPI),
                 "--turn", "ccw", "--store", str(tmp_path / "store")]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "JPEG" in line]
    assert len(warnings) == 1 and warnings[0].startswith("warning: F-jpg: 4 JPEG scan(s)")
    assert "scan_0.jpg" in warnings[0] and "lossy" in warnings[0] and "normals" in warnings[0]
    [art] = _scans_files(tmp_path / "store")
    with h5py.File(art) as f:
        assert f["front/scan_0"].dtype == np.uint8 and len([k for k in f["front"] if k.startswith("scan_")]) == 4
    # PNG scans: no such warning
    png = _write(tmp_path, scans, eight=True)
    assert main(["import", "scans", *png, "--fragment", "F-png", "--device", "files", "--dpi", str(DPI),
                 "--turn", "ccw", "--store", str(tmp_path / "store")]) == 0
    assert "JPEG" not in capsys.readouterr().err


@pytest.mark.parametrize("problem, expected", [
    ("truncated", "scan_2.png"),
    ("two scans", "normals need at least 3"),
    ("8-bit in 16", "8-bit values"),
    ("other face", "scan 3 "),
])
def test_bad_scans_are_refused_naming_the_file_and_nothing_is_written(tmp_path, turned_scans, capsys, problem,
                                                                      expected):
    _, scans = turned_scans
    scans = list(scans)
    if problem == "8-bit in 16":
        scans[1] = (scans[1] // 257).astype(np.uint16)
    if problem == "other face":      # the fragment flipped before the last scan
        other = SimulatedFlatbed("files", bed_mm=(100, 100), seed=13)
        other.place(demo_surface(25, DPI, seed=4), centre_mm=(50, 50))
        other.flip()
        scans[3] = other.scan(AREA, DPI)
    paths = _write(tmp_path, scans)
    if problem == "truncated":
        data = open(paths[2], "rb").read()
        open(paths[2], "wb").write(data[:len(data) // 2])
    if problem == "two scans":
        paths = paths[:2]
    assert main(["import", "scans", *paths, "--fragment", "F-imp-4", "--device", "files", "--dpi", str(DPI),
                 "--store", str(tmp_path / "store")]) == 1
    out = capsys.readouterr()
    assert expected in out.out + out.err
    assert not _scans_files(tmp_path / "store")


def test_a_manifest_imports_each_fragment_and_refuses_only_the_bad_one(tmp_path, turned_scans, capsys):
    _, scans = turned_scans
    good = _write(tmp_path, scans)
    (tmp_path / "bad").mkdir()
    bad = _write(tmp_path / "bad", [scans[0], scans[1]], eight=True)   # not copies of good's: another fragment
    manifest = tmp_path / "scans.csv"
    lines = ["file,fragment,face,dpi,turn"] + [f"{p},Inv 7/1,front,{DPI},ccw" for p in good] + \
            [f"{p},Inv 7/2,front,{DPI},auto" for p in bad]
    manifest.write_text("\n".join(lines) + "\n")
    assert main(["import", "scans", "--manifest", str(manifest), "--device", "files",
                 "--store", str(tmp_path / "store")]) == 1
    out = capsys.readouterr()
    assert "normals need at least 3" in out.out + out.err
    [art] = _scans_files(tmp_path / "store")
    assert "Inv-7-1" in str(art)


def test_a_manifest_whose_rows_give_one_fragment_two_turns_is_refused_before_anything_is_written(
        tmp_path, turned_scans, capsys):
    # the turn was taken from the fragment's first row, silently: now the conflict is named
    _, scans = turned_scans
    good = _write(tmp_path, scans)
    manifest = tmp_path / "scans.csv"
    # line 2: another fragment, listed first (nothing of it is written either); Inv 7/1 on lines 3-6:
    # ccw, no value (empty cells do not count), cw, ccw
    lines = ["file,fragment,dpi,turn", f"{good[0]},Inv 7/0,{DPI},auto"] + \
            [f"{p},Inv 7/1,{DPI},{t}" for p, t in zip(good, ["ccw", "", "cw", "ccw"])]
    manifest.write_text("\n".join(lines) + "\n")
    assert main(["import", "scans", "--manifest", str(manifest), "--device", "files",
                 "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert "fragment Inv-7-1" in err and "'ccw'" in err and "'cw'" in err
    assert "line 3" in err and "line 5" in err
    assert not _scans_files(tmp_path / "store") and not (tmp_path / "store" / "imports").exists()
    # the dpi column likewise
    lines = ["file,fragment,dpi"] + [f"{p},Inv 7/1,{d}" for p, d in zip(good, [DPI, "", DPI, 300])]
    manifest.write_text("\n".join(lines) + "\n")
    assert main(["import", "scans", "--manifest", str(manifest), "--device", "files",
                 "--store", str(tmp_path / "store")]) == 2
    err = capsys.readouterr().err
    assert f"fragment Inv-7-1: dpi {DPI} (" in err and "line 4" in err and "dpi 300 (line 5)" in err
    assert not _scans_files(tmp_path / "store")


def test_srgb_does_not_decode_float_scans_which_are_linear(tmp_path):
    # docs/flatbed.md: float scans are linear with full scale 1; --srgb (for 8/16-bit files of a
    # whole batch) once decoded their 16-bit conversion as if it were [0, 1] and saturated them
    from services.cli.import_scans import _read_scan
    scan = np.full((60, 60, 3), 0.1, np.float32)
    scan[20:40, 20:40] = 0.5
    np.save(tmp_path / "s.npy", scan)
    opts = {"dpi": DPI, "crop": False}
    linear, _ = _read_scan(tmp_path / "s.npy", {**opts, "srgb": False})
    decoded, _ = _read_scan(tmp_path / "s.npy", {**opts, "srgb": True})
    assert linear.dtype == np.uint16 and linear.max() == 32768
    np.testing.assert_array_equal(decoded, linear)


def test_the_same_scans_under_a_second_id_are_refused_naming_the_first(tmp_path, turned_scans, capsys):
    """The same scan set imported again under another id (a manifest's inventory number, then --fragment) made a
    second fragment, which the matcher proposed as a join to the first. Any scan of a set that was imported as
    another fragment makes the set that fragment again: refused naming it and the file, unless
    ``--allow-duplicates``; found from the ledger, or from the scans artifact's provenance when another bench
    imported it."""
    _, scans = turned_scans
    store = tmp_path / "store"
    paths = _write(tmp_path, scans)
    rows = "".join(f"{p},Inv 7/1,{DPI},ccw\n" for p in paths)
    (tmp_path / "scans.csv").write_text("file,inventory,dpi,turn\n" + rows)
    assert main(["import", "scans", "--manifest", str(tmp_path / "scans.csv"), "--device", "files",
                 "--store", str(store)]) == 0
    capsys.readouterr()
    base = ["--device", "files", "--dpi", str(DPI), "--turn", "ccw", "--store", str(store)]
    assert main(["import", "scans", *paths, "--fragment", "F-again", *base]) == 1
    out = capsys.readouterr()
    assert "imported 0, already imported 0, refused 1" in out.out
    assert ("refused F-again: scan_0.png: the same file (sha256 " in out.err
            and f"is already imported as fragment Inv-7-1 (front, {DPI} dpi: fragments/Inv-7-1/scans/scans-" in out.err
            and "not imported again as F-again (front): give --allow-duplicates" in out.err), out.err
    # one scan of the set taken again is still the same fragment: the other three are its
    (tmp_path / "retaken").mkdir()
    retaken = _write(tmp_path / "retaken", scans[:1], eight=True) + paths[1:]
    assert main(["import", "scans", *retaken, "--fragment", "F-retaken", *base]) == 1
    assert "refused F-retaken: scan_1.png: the same file" in capsys.readouterr().err
    assert [f.parts[-3] for f in _scans_files(store)] == ["Inv-7-1"]
    # imported by another bench (no ledger here): found from the artifact's provenance (source_sha256, dpi)
    (store / "imports" / "ledger.jsonl").unlink()
    assert main(["import", "scans", *paths, "--fragment", "F-again", *base]) == 1
    err = capsys.readouterr().err
    assert f"already imported as fragment Inv-7-1 (front, {DPI} dpi: fragments/Inv-7-1/scans/" in err
    # asked for, it goes in
    assert main(["import", "scans", *paths, "--fragment", "F-again", "--allow-duplicates", *base]) == 0
    assert sorted(f.parts[-3] for f in _scans_files(store)) == ["F-again", "Inv-7-1"]


def test_the_same_scans_at_another_dpi_are_refused_naming_both_unless_replace(tmp_path, turned_scans, capsys):
    """The same scans imported again for the same fragment at another dpi made a second, rescaled scan set (and
    face): refused naming both dpi values; ``--replace`` imports it, and the same dpi with other options (here
    --turn given instead of detected) replaces the set as before."""
    _, scans = turned_scans
    store = tmp_path / "store"
    paths = _write(tmp_path, scans)
    base = [*paths, "--fragment", "F-dpi", "--device", "files", "--store", str(store)]
    assert main(["import", "scans", *base, "--dpi", str(DPI)]) == 0
    assert main(["import", "scans", *base, "--dpi", str(DPI), "--turn", "ccw"]) == 0   # same dpi: not refused
    capsys.readouterr()
    assert main(["import", "scans", *base, "--dpi", "160"]) == 1
    err = capsys.readouterr().err
    assert (f"refused F-dpi: scan_0.png: the same file is already imported for fragment F-dpi (front) at {DPI} dpi; "
            f"this import gives 160 dpi: give --replace to make the 160 dpi face replace the {DPI} dpi one") in err
    assert len(_scans_files(store)) == 2
    assert main(["import", "scans", *base, "--dpi", "160", "--replace"]) == 0
    assert len(_scans_files(store)) == 3
