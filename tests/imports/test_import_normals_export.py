"""``tessera import normals`` and ``tessera export``: files of other tools in, the same files out."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.rgbn.image import RGBNImage, load_rgbn, save_rgbn
from common.rgbn.io import encode_normal_map, linear_to_srgb, write_image
from common.store import Store
from services.cli import main
from tests.imports.test_normals import _angle_deg, _surface_normals


def _albedo(mask):
    h, w = mask.shape
    yy, xx = np.mgrid[0:h, 0:w]
    a = np.dstack([0.5 + 0.3 * np.sin(xx / 20.0), 0.3 + 0.1 * np.cos(yy / 9.0), np.full((h, w), 0.15)])
    return (a * mask[..., None]).astype(np.float32)


def _write_capture(folder, convention="opengl", bits=16):
    """A Relight-like output folder: normals.png (with alpha) and albedo.png (sRGB)."""
    n, mask = _surface_normals()
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / "normals.png", encode_normal_map(n, mask, convention), bits=bits, alpha=mask.astype(float))
    write_image(folder / "albedo.png", linear_to_srgb(_albedo(mask)), bits=8)
    return n, mask


def _faces(root):
    return sorted((root / "fragments").rglob("rgbn/*.h5"))


@pytest.mark.parametrize("convention", ["opengl", "directx"])
def test_relight_folder_is_imported_with_its_convention(tmp_path, convention):
    n, mask = _write_capture(tmp_path / "in" / "T-0042", convention)
    args = ["import", "normals", str(tmp_path / "in" / "T-0042"), "--dpi", "600", "--store", str(tmp_path / "st")]
    assert main(args + ["--convention", convention]) == 0
    (face,) = _faces(tmp_path / "st")
    assert face.parts[-3] == "T-0042"
    img = load_rgbn(Store(tmp_path / "st"), face.relative_to(tmp_path / "st").as_posix())
    np.testing.assert_array_equal(img.mask, mask)
    assert _angle_deg(img.normals[mask], n[mask]).max() < 0.01
    np.testing.assert_allclose(img.albedo[mask], _albedo(mask)[mask], atol=0.01)   # 8-bit sRGB
    assert img.attrs["source_convention"] == convention and img.dpi == 600


def test_directx_map_declared_opengl_is_refused_and_auto_finds_it(tmp_path, capsys):
    _write_capture(tmp_path / "in" / "dx", "directx", bits=8)
    base = ["import", "normals", str(tmp_path / "in" / "dx"), "--dpi", "300", "--store", str(tmp_path / "st")]
    assert main(base) == 1
    assert "declared opengl but the map reads as directx" in capsys.readouterr().err
    assert not _faces(tmp_path / "st")
    assert main(base + ["--convention", "auto"]) == 0
    (face,) = _faces(tmp_path / "st")
    assert load_rgbn(Store(tmp_path / "st"), face.relative_to(tmp_path / "st").as_posix()).attrs[
        "source_convention"] == "directx"


def test_photograph_given_as_normal_map_is_refused(tmp_path, capsys):
    rng = np.random.default_rng(1)
    photo = np.clip(rng.normal([60, 110, 170], 20, (120, 160, 3)), 0, 255).astype(np.uint8)  # BGR: ochre
    cv2.imwrite(str(tmp_path / "P7_normals.png"), photo)
    assert main(["import", "normals", str(tmp_path / "P7_normals.png"), "--dpi", "300",
                 "--store", str(tmp_path / "st")]) == 1
    err = capsys.readouterr().err
    assert "P7_normals.png: it does not look like a normal map" in err
    assert not (tmp_path / "st" / "fragments").exists()


def test_albedo_of_another_size_is_refused(tmp_path, capsys):
    _write_capture(tmp_path / "in")
    cv2.imwrite(str(tmp_path / "small.png"), np.repeat(np.linspace(40, 200, 50, dtype=np.uint8)[None, :, None], 50, 0)
                .repeat(3, 2))
    assert main(["import", "normals", str(tmp_path / "in" / "normals.png"), "--albedo", str(tmp_path / "small.png"),
                 "--fragment", "F1", "--dpi", "300", "--store", str(tmp_path / "st")]) == 1
    assert "must share a pixel grid" in capsys.readouterr().err


def test_the_same_map_under_a_second_id_is_refused_naming_the_first(tmp_path, capsys):
    """A normal map (or its albedo) imported once as a folder's fragment and again under another id made a second
    fragment, proposed as a join to the first: refused naming the fragment it is and the file, unless
    ``--allow-duplicates``; the other face of the same fragment likewise."""
    _write_capture(tmp_path / "in" / "T-0042")
    st = ["--store", str(tmp_path / "st")]
    assert main(["import", "normals", str(tmp_path / "in" / "T-0042"), "--dpi", "600", *st]) == 0
    capsys.readouterr()
    again = ["import", "normals", str(tmp_path / "in" / "T-0042" / "normals.png"), "--albedo",
             str(tmp_path / "in" / "T-0042" / "albedo.png"), "--fragment", "Inv. 42", "--dpi", "600", *st]
    assert main(again) == 1
    out = capsys.readouterr()
    assert "imported 0, already imported 0, refused 1" in out.out
    assert ("refused T-0042/normals.png: normals.png: the same file (sha256 " in out.err
            and "is already imported as fragment T-0042 (front, 600 dpi: fragments/T-0042/rgbn/front-" in out.err
            and "not imported again as Inv.-42 (front): give --allow-duplicates" in out.err), out.err
    # only the albedo is the same file (the map re-encoded at 8 bits): the same fragment still
    (tmp_path / "b").mkdir()
    n, mask = _surface_normals()
    write_image(tmp_path / "b" / "X_normals.png", encode_normal_map(n, mask, "opengl"), bits=8,
                alpha=mask.astype(float))
    assert main(["import", "normals", str(tmp_path / "b" / "X_normals.png"), "--albedo",
                 str(tmp_path / "in" / "T-0042" / "albedo.png"), "--dpi", "600", *st]) == 1
    assert "refused X_normals.png: albedo.png: the same file" in capsys.readouterr().err
    # the other face of the same fragment is refused too
    assert main(["import", "normals", str(tmp_path / "in" / "T-0042"), "--dpi", "600", "--face", "back", *st]) == 1
    assert "already imported as fragment T-0042 (front, 600 dpi" in capsys.readouterr().err
    assert [f.parts[-3] for f in _faces(tmp_path / "st")] == ["T-0042"]
    assert main(again + ["--allow-duplicates"]) == 0
    assert sorted(f.parts[-3] for f in _faces(tmp_path / "st")) == ["Inv.-42", "T-0042"]


def test_the_same_map_at_another_dpi_is_refused_naming_both_unless_replace(tmp_path, capsys):
    """Re-importing a normal map for the same fragment at another dpi added a second, rescaled face: refused
    naming both dpi values; ``--replace`` imports it, the new face the one every stage and page uses."""
    from common.imports.export import latest_faces

    _write_capture(tmp_path / "in" / "T-7")
    args = ["import", "normals", str(tmp_path / "in" / "T-7"), "--store", str(tmp_path / "st")]
    assert main(args + ["--dpi", "600"]) == 0
    assert main(args + ["--dpi", "600", "--convention", "auto"]) == 0   # the same dpi, other options: as before
    capsys.readouterr()
    assert main(args + ["--dpi", "300"]) == 1
    assert ("refused T-7/normals.png: normals.png: the same file is already imported for fragment T-7 (front) at "
            "600 dpi; this import gives 300 dpi: give --replace to make the 300 dpi face replace the 600 dpi one"
            ) in capsys.readouterr().err
    assert len(_faces(tmp_path / "st")) == 2
    assert main(args + ["--dpi", "300", "--replace"]) == 0
    newest = latest_faces(Store(tmp_path / "st"), "T-7")["front"]
    assert load_rgbn(Store(tmp_path / "st"), newest).dpi == 300


def test_export_then_import_gives_the_same_face(tmp_path):
    """Round trip: the 16-bit OpenGL normal map and the albedo of an export read back within quantisation."""
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    face = RGBNImage(albedo=_albedo(mask), mask=mask, dpi=450.0, normals=np.where(mask[..., None], n, (0, 0, 1)),
                     attrs={"metadata": json.dumps({"inventory": "Inv. 7", "find_spot": "Room 2"})})
    save_rgbn(store, "fragments/Inv.-7/rgbn/front-abc.h5", face)
    save_rgbn(store, "fragments/Inv.-8/rgbn/front-def.h5",
              RGBNImage(albedo=_albedo(mask), mask=mask, dpi=450.0))            # colour-only
    assert main(["export", "--all", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    out = tmp_path / "out"
    assert sorted(p.name for p in (out / "Inv.-7").iterdir()) == ["front-albedo.png", "front-normals.png",
                                                                 "metadata.json"]
    assert sorted(p.name for p in (out / "Inv.-8").iterdir()) == ["front-albedo.png", "metadata.json"]
    assert json.loads((out / "collection.json").read_text())["fragments"] == ["Inv.-7", "Inv.-8"]
    raw = cv2.imread(str(out / "Inv.-7" / "front-normals.png"), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.shape[2] == 4
    # OpenGL: green grows towards the top row where the surface faces up (ny > 0)
    up = mask & (n[..., 1] > 0.3)
    assert (raw[..., 1][up] > 32768).all()
    meta = json.loads((out / "Inv.-7" / "metadata.json").read_text())
    assert meta["faces"]["front"]["metadata"] == {"inventory": "Inv. 7", "find_spot": "Room 2"}
    assert meta["faces"]["front"]["dpi"] == 450.0 and "OpenGL" in meta["normal_map"]
    # back in through the importer (dpi and metadata from metadata.json)
    assert main(["import", "normals", str(out / "Inv.-7"), "--store", str(tmp_path / "st2")]) == 0
    (back,) = _faces(tmp_path / "st2")
    assert back.parts[-3] == "Inv.-7"
    img = load_rgbn(Store(tmp_path / "st2"), back.relative_to(tmp_path / "st2").as_posix())
    np.testing.assert_array_equal(img.mask, mask)
    assert _angle_deg(img.normals[mask], n[mask]).max() < np.degrees(np.sqrt(3) / 65535)
    np.testing.assert_allclose(img.albedo[mask], face.albedo[mask], atol=2e-4)  # 16-bit sRGB
    assert img.dpi == 450.0
    assert json.loads(img.attrs["metadata"])["inventory"] == "Inv. 7"


def test_export_refuses_unknown_fragment_and_existing_folder(tmp_path, capsys):
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    save_rgbn(store, "fragments/A/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0))
    assert main(["export", "A", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    assert main(["export", "A", "NOPE", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 1
    err = capsys.readouterr().err
    assert "not exported A:" in err and "exists" in err
    assert "not exported NOPE: fragment NOPE has no RGBN face" in err
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]   # no temporary left


@pytest.mark.parametrize("umask", [0o022, 0o027])
def test_an_export_is_readable_as_the_umask_allows(tmp_path, umask):
    """An export is for other people and tools, but its fragment folders were made by mkdtemp (mode 0700) and
    collection.json by the store's temporary file (0600): a colleague could open neither. They follow the umask,
    as the files in the folders always did."""
    import os
    import stat

    _, mask = _surface_normals()
    store = Store(tmp_path / "st")
    for fid in ("A", "B"):
        save_rgbn(store, f"fragments/{fid}/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0))
    old = os.umask(umask)
    try:
        assert main(["export", "A", "B", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    finally:
        os.umask(old)
    out = tmp_path / "out"
    mode = lambda p: stat.S_IMODE(p.stat().st_mode)  # noqa: E731
    for fid in ("A", "B"):
        assert mode(out / fid) == 0o777 & ~umask, fid
        assert {f.name: mode(f) for f in (out / fid).iterdir()} == {
            f.name: 0o666 & ~umask for f in (out / fid).iterdir()}
    assert mode(out / "collection.json") == 0o666 & ~umask


def _free_space(monkeypatch, free):
    """shutil.disk_usage answering ``free`` bytes for every path; returns the paths it was asked about."""
    import collections
    import shutil
    asked = []
    usage = collections.namedtuple("usage", "total used free")

    def disk_usage(path):
        asked.append(Path(path))
        return usage(10 ** 12, 10 ** 12 - free, free)
    monkeypatch.setattr(shutil, "disk_usage", disk_usage)
    return asked


def test_export_checks_the_free_space_of_its_destination_before_writing_anything(tmp_path, monkeypatch, capsys):
    import re

    from common.store import FREE_SPACE_MARGIN_BYTES
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    for fid in ("A", "B"):
        save_rgbn(store, f"fragments/{fid}/rgbn/front-1.h5",
                  RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0, normals=n))
    assert main(["export", "A", "-o", str(tmp_path / "probe"), "--store", str(tmp_path / "st")]) == 0
    size = sum(p.stat().st_size for p in (tmp_path / "probe" / "A").iterdir())   # what an export of A writes
    capsys.readouterr()
    # a disk with less than the files + the margin: refused before anything is written, sizes named
    free = size + FREE_SPACE_MARGIN_BYTES - 2000
    asked = _free_space(monkeypatch, free)
    out = tmp_path / "usb" / "out"
    assert main(["export", "A", "B", "-o", str(out), "--store", str(tmp_path / "st")]) == 1
    err = capsys.readouterr().err
    assert "not enough free space, stopped at A" in err and f"{free} free" in err and "1 more fragment(s) not tried" in err
    assert "stopped at A: storage full: the export of A" in err and "Errno" not in err   # as docs/import.md quotes it
    need = int(re.search(r"needs (\d+) bytes", err).group(1))
    assert abs(need - size) < 100       # the sum of the files (metadata.json's time stamp aside)
    assert not (tmp_path / "usb").exists()
    assert asked and asked[-1] == tmp_path   # the destination's file system: its nearest existing folder
    # with the room, the same export goes through
    _free_space(monkeypatch, size + FREE_SPACE_MARGIN_BYTES + 2000)
    assert main(["export", "A", "-o", str(out), "--store", str(tmp_path / "st")]) == 0
    assert sorted(p.name for p in (out / "A").iterdir()) == ["front-albedo.png", "front-normals.png", "metadata.json"]


def test_export_all_of_a_one_fragment_store_writes_collection_json(tmp_path):
    """docs/import.md: "With several fragments (or --all) OUT/collection.json lists them"; --all on a store of
    one fragment wrote none (only len(ids) > 1 counted). A single fragment named writes none, as before."""
    _, mask = _surface_normals()
    save_rgbn(Store(tmp_path / "st"), "fragments/A/rgbn/front-1.h5",
              RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0))
    assert main(["export", "--all", "-o", str(tmp_path / "all"), "--store", str(tmp_path / "st")]) == 0
    assert json.loads((tmp_path / "all" / "collection.json").read_text())["fragments"] == ["A"]
    assert main(["export", "A", "-o", str(tmp_path / "one"), "--store", str(tmp_path / "st")]) == 0
    assert (tmp_path / "one" / "A").is_dir() and not (tmp_path / "one" / "collection.json").exists()


def test_renders_on_storage_are_exported_as_pngs(tmp_path):
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    save_rgbn(store, "fragments/R1/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0, normals=n))
    drawn = (np.random.default_rng(0).random(mask.shape + (3,)) * 65535).astype(np.uint16)

    def fill(f):   # what common.render.artifact.save_rendering writes
        f.create_dataset("image", data=drawn)
        f.create_dataset("alpha", data=(mask * 65535).astype(np.uint16))
        f.attrs["recipe"] = "relief"
        f.attrs["bits"] = 16
    store.write("fragments/R1/renders/front-0123456789abcdef.h5", "tessera.render", 1, fill)
    assert main(["export", "R1", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    png = tmp_path / "out" / "R1" / "front-render-relief-01234567.png"
    raw = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    np.testing.assert_array_equal(raw[..., [2, 1, 0]], drawn)
    np.testing.assert_array_equal(raw[..., 3] > 0, mask)
    meta = json.loads((tmp_path / "out" / "R1" / "metadata.json").read_text())
    assert png.name in meta["faces"]["front"]["files"]


def _three_fragments(tmp_path, monkeypatch, capsys) -> int:
    """Fragments A, B, C with the same face on storage; the bytes the export of one writes (A's, exported alone)."""
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    for fid in ("A", "B", "C"):
        save_rgbn(store, f"fragments/{fid}/rgbn/front-1.h5",
                  RGBNImage(albedo=_albedo(mask), mask=mask, dpi=300.0, normals=n))
    assert main(["export", "A", "-o", str(tmp_path / "probe"), "--store", str(tmp_path / "st")]) == 0
    capsys.readouterr()
    return sum(p.stat().st_size for p in (tmp_path / "probe" / "A").iterdir())


@pytest.mark.parametrize("keep", [None, 0], ids=["kept-from-sizing", "encoded-again"])
def test_export_all_that_does_not_fit_is_refused_before_any_fragment_is_written(tmp_path, monkeypatch, capsys, keep):
    import re

    from common.imports import export
    from common.store import FREE_SPACE_MARGIN_BYTES
    size = _three_fragments(tmp_path, monkeypatch, capsys)
    out = tmp_path / "usb" / "out"
    # room for two fragments, not three: the per-fragment check alone wrote A and B, then stopped at C
    free = 2 * size + FREE_SPACE_MARGIN_BYTES + 5000
    _free_space(monkeypatch, free)
    assert main(["export", "--all", "-o", str(out), "--store", str(tmp_path / "st")]) == 1
    err = capsys.readouterr().err
    assert "not enough free space for --all" in err and "nothing was written" in err and f"{free} free" in err
    assert abs(int(re.search(r"needs (\d+) bytes", err).group(1)) - 3 * size) < 300   # the three fragments' files
    assert not (tmp_path / "usb").exists()
    # with room for the three: all written, the same files as each exported alone (encoded once or twice)
    if keep is not None:
        real = export.size_export
        monkeypatch.setattr(export, "size_export", lambda *a, **k: real(*a, **{**k, "keep_bytes": keep}))
    _free_space(monkeypatch, 3 * size + FREE_SPACE_MARGIN_BYTES + 5000)
    assert main(["export", "--all", "-o", str(out), "--store", str(tmp_path / "st")]) == 0
    assert json.loads((out / "collection.json").read_text())["fragments"] == ["A", "B", "C"]
    for fid in ("A", "B", "C"):
        for png in ("front-albedo.png", "front-normals.png"):
            assert (out / fid / png).read_bytes() == (tmp_path / "probe" / "A" / png).read_bytes(), (fid, png)


def test_export_all_still_checks_each_fragment_for_a_disk_filled_meanwhile(tmp_path, monkeypatch, capsys):
    import collections
    import shutil

    from common.store import FREE_SPACE_MARGIN_BYTES
    size = _three_fragments(tmp_path, monkeypatch, capsys)
    # the whole export fits when sized; then another writer leaves room for A only
    answers = iter([3 * size + FREE_SPACE_MARGIN_BYTES + 5000, size + FREE_SPACE_MARGIN_BYTES + 5000])
    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda path: usage(10 ** 12, 0, next(answers, 1000)))
    out = tmp_path / "out"
    assert main(["export", "--all", "-o", str(out), "--store", str(tmp_path / "st")]) == 1
    err = capsys.readouterr().err
    assert "not enough free space, stopped at B" in err and "1 more fragment(s) not tried" in err
    assert sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith(".")) == ["A"]
    assert sorted(p.name for p in (out / "A").iterdir()) == ["front-albedo.png", "front-normals.png", "metadata.json"]


def test_exported_pictures_declare_the_faces_dpi(tmp_path):
    """Albedo, normal map and renders carry the face's dpi (PNG pHYs), not only metadata.json: a picture
    opened alone in an image editor or ImageJ measures in mm."""
    from PIL import Image

    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    save_rgbn(store, "fragments/D1/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=187.5, normals=n))

    def fill(f):   # what common.render.artifact.save_rendering writes
        f.create_dataset("image", data=np.zeros(mask.shape + (3,), np.uint8))
        f.create_dataset("alpha", data=(mask * 255).astype(np.uint8))
        f.attrs["recipe"] = "relief"
        f.attrs["bits"] = 8
    store.write("fragments/D1/renders/front-0123456789abcdef.h5", "tessera.render", 1, fill)
    assert main(["export", "D1", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    names = ["front-albedo.png", "front-normals.png", "front-render-relief-01234567.png"]
    assert sorted(p.name for p in (tmp_path / "out" / "D1").glob("*.png")) == sorted(names)
    for name in names:
        with Image.open(tmp_path / "out" / "D1" / name) as im:
            assert im.info.get("dpi") == pytest.approx((187.5, 187.5), rel=1e-4), name   # whole px per metre


def test_a_colour_only_fragments_export_describes_no_normal_map(tmp_path):
    """A fragment imported from a picture has no normals: its export writes no normal map and its metadata.json
    does not describe one (a reader would look for a file that is not there); with normals it does."""
    n, mask = _surface_normals()
    store = Store(tmp_path / "st")
    save_rgbn(store, "fragments/C1/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=150.0))
    save_rgbn(store, "fragments/N1/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=150.0, normals=n))
    assert main(["export", "C1", "N1", "-o", str(tmp_path / "out"), "--store", str(tmp_path / "st")]) == 0
    colour = json.loads((tmp_path / "out" / "C1" / "metadata.json").read_text())
    assert colour["faces"]["front"]["has_normals"] is False and "normal_map" not in colour
    assert not (tmp_path / "out" / "C1" / "front-normals.png").exists()
    relief = json.loads((tmp_path / "out" / "N1" / "metadata.json").read_text())
    assert relief["faces"]["front"]["has_normals"] is True and "OpenGL" in relief["normal_map"]


def _store_of_three(tmp_path):
    """A store of fragments A, B, C (colour only) and a proposal database: A-B confirmed at a pose set on the
    review page, B-C confirmed then rejected, A-C confirmed at a pose given from C's side."""
    from common.matching.proposals import ProposalStore

    _, mask = _surface_normals()
    store = Store(tmp_path / "st")
    for fid in "ABC":
        save_rgbn(store, f"fragments/{fid}/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=150.0))
    with ProposalStore(tmp_path / "st" / "matches" / "proposals.sqlite") as db:
        db.record_verdict("A", "B", "confirmed", by="conservator", when=1.0e9,
                          pose={"angle_deg": 90.0, "tx_mm": 10.0, "ty_mm": 0.0})
        db.record_verdict("B", "C", "confirmed", pose={"angle_deg": 0.0, "tx_mm": 5.0, "ty_mm": 0.0})
        db.record_verdict("B", "C", "rejected")                  # changed their mind
        db.record_verdict("C", "A", "confirmed", pose={"angle_deg": 0.0, "tx_mm": 0.0, "ty_mm": 7.0})
    return store


def test_an_export_carries_the_confirmed_joins_with_their_poses(tmp_path):
    """The conservator's confirmed joins go with the export: each fragment's metadata.json lists its own, the other
    fragment's pose in this one's frame (p_this = R p_other + t), and collection.json those between the fragments
    it lists; a rejected join, and a join to a fragment not exported, are not in collection.json."""
    from common.matching.alignment import pose_matrix

    _store_of_three(tmp_path)
    out = tmp_path / "out"
    assert main(["export", "A", "B", "-o", str(out), "--store", str(tmp_path / "st")]) == 0
    a = json.loads((out / "A" / "metadata.json").read_text())["joins"]
    b = json.loads((out / "B" / "metadata.json").read_text())["joins"]
    assert [j["other"] for j in a] == ["B", "C"] and [j["other"] for j in b] == ["A"]   # B-C was rejected
    ab = a[0]
    assert (ab["angle_deg"], ab["tx_mm"], ab["ty_mm"]) == pytest.approx((90.0, 10.0, 0.0))
    assert ab["by"] == "conservator" and ab["time"] == 1.0e9
    ba = b[0]                      # the same join seen from B: the inverse transform
    np.testing.assert_allclose(pose_matrix(ab["angle_deg"], ab["tx_mm"], ab["ty_mm"])
                               @ pose_matrix(ba["angle_deg"], ba["tx_mm"], ba["ty_mm"]), np.eye(3), atol=1e-9)
    ac = a[1]                      # given from C's side (A 7 mm down in C's frame): C is 7 mm up in A's
    assert (ac["angle_deg"], ac["tx_mm"], ac["ty_mm"]) == pytest.approx((0.0, 0.0, -7.0))
    listed = json.loads((out / "collection.json").read_text())
    assert listed["fragments"] == ["A", "B"]
    assert [(j["fragment"], j["other"]) for j in listed["joins"]] == [("A", "B")]      # C not exported
    assert (listed["joins"][0]["angle_deg"], listed["joins"][0]["tx_mm"]) == pytest.approx((90.0, 10.0))
    # the whole collection (sized first, then written): both confirmed joins
    assert main(["export", "--all", "-o", str(tmp_path / "all"), "--store", str(tmp_path / "st")]) == 0
    listed = json.loads((tmp_path / "all" / "collection.json").read_text())
    assert [(j["fragment"], j["other"]) for j in listed["joins"]] == [("A", "B"), ("A", "C")]
    assert [j["other"] for j in json.loads((tmp_path / "all" / "C" / "metadata.json").read_text())["joins"]] == ["A"]


def test_an_export_without_a_readable_proposal_database_still_exports_the_faces(tmp_path, capsys):
    """No database (no matcher ran): no joins key, nothing said. --db naming a missing file is refused up front.
    A database that cannot be read is said on stderr and the faces are exported without joins."""
    _, mask = _surface_normals()
    store = Store(tmp_path / "st")
    save_rgbn(store, "fragments/A/rgbn/front-1.h5", RGBNImage(albedo=_albedo(mask), mask=mask, dpi=150.0))
    assert main(["export", "A", "-o", str(tmp_path / "o1"), "--store", str(tmp_path / "st")]) == 0
    assert "joins" not in json.loads((tmp_path / "o1" / "A" / "metadata.json").read_text())
    missing = tmp_path / "nowhere.sqlite"
    assert main(["export", "A", "-o", str(tmp_path / "o2"), "--store", str(tmp_path / "st"), "--db", str(missing)]) == 2
    assert f"no proposal database at {missing}" in capsys.readouterr().err and not (tmp_path / "o2").exists()
    (tmp_path / "st" / "matches").mkdir()
    (tmp_path / "st" / "matches" / "proposals.sqlite").write_bytes(b"not a database" * 100)
    assert main(["export", "A", "-o", str(tmp_path / "o3"), "--store", str(tmp_path / "st")]) == 0
    err = capsys.readouterr().err
    assert "proposal database" in err and "cannot be read" in err and "without their joins" in err
    assert "joins" not in json.loads((tmp_path / "o3" / "A" / "metadata.json").read_text())
