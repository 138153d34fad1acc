"""``tessera import rti``: capture folders -> RGBN faces through the same path as ``tessera ps``."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from common.acquisition.handheld import simulate_flash_capture, surface_normals
from common.acquisition.lightfile import write_lp
from common.acquisition.surface import FragmentSurface
from common.rgbn.image import load_rgbn
from common.store import Store
from services.cli import main as tessera


def _lights(n, seed=3):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(30, 80, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _surface(size=48, tilt=0.3):
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    mask = (np.abs(cols - size / 2) < size * 0.35) & (np.abs(rows - size / 2) < size * 0.3)
    height = (tilt * cols + 0.1 * np.sin(rows / 4)) * 0.1 + 1.0
    albedo = np.dstack([np.full((size, size), v) for v in (0.8, 0.6, 0.4)]).astype(np.float32)
    return FragmentSurface(albedo, np.where(mask, height, 0.0), mask, 254.0)


def _capture(folder, n=12, lp=True, tilt=0.3):
    folder.mkdir(parents=True)
    surf = _surface(tilt=tilt)
    lights = _lights(n)
    names = [f"img{i}.png" for i in range(n)]
    for name, img in zip(names, simulate_flash_capture(surf, lights)):
        cv2.imwrite(str(folder / name), np.round(img * 65535).astype(np.uint16)[..., ::-1])
    if lp:
        write_lp(folder / "capture.lp", names, lights)
    return surf


def _artifacts(root):
    return sorted(p.relative_to(root).as_posix() for p in (root / "fragments").rglob("*.h5")) \
        if (root / "fragments").exists() else []


def test_a_collection_of_captures_becomes_one_fragment_each(tmp_path, capsys):
    a = _capture(tmp_path / "coll" / "F-A", tilt=0.3)
    b = _capture(tmp_path / "coll" / "F-B", tilt=-0.2)
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(tmp_path / "coll"), "--store", str(store), "--no-discontinuities"]) == 0
    assert "imported 2" in capsys.readouterr().out
    found = _artifacts(store)
    assert [p.split("/")[1] for p in found] == ["F-A", "F-B"]
    for rel, surf in zip(found, (a, b)):
        rgbn = load_rgbn(Store(store), rel)
        inner = cv2.erode(surf.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        err = np.degrees(np.arccos(np.clip((rgbn.normals * surface_normals(surf)).sum(-1), -1, 1)))
        assert err[inner].mean() < 1.0
        assert rgbn.mask[inner].all()  # the automatic mask found the piece
    # resumable: a second run imports nothing again
    assert tessera(["import", "rti", str(tmp_path / "coll"), "--store", str(store), "--no-discontinuities"]) == 0
    assert "imported 0, already imported 2" in capsys.readouterr().out


def test_bad_captures_are_refused_by_name_and_the_good_one_imported(tmp_path, capsys):
    _capture(tmp_path / "coll" / "good")
    _capture(tmp_path / "coll" / "cut", tilt=-0.2)   # three fragments (the same pictures would be one: refused)
    shot = tmp_path / "coll" / "cut" / "img4.png"
    shot.write_bytes(shot.read_bytes()[:600])
    _capture(tmp_path / "coll" / "nolights", lp=False, tilt=0.1)
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(tmp_path / "coll"), "--store", str(store), "--no-discontinuities"]) == 1
    captured = capsys.readouterr()
    assert "imported 1" in captured.out and "refused 2" in captured.out
    assert "img4.png" in captured.err and "truncated" in captured.err
    assert "nolights" in captured.err and "no light file" in captured.err
    assert [p.split("/")[1] for p in _artifacts(store)] == ["good"]


def test_a_plain_direction_file_pairs_images_in_natural_order(tmp_path, capsys):
    surf = _capture(tmp_path / "cap", lp=False)
    np.savetxt(tmp_path / "cap" / "dirs.txt", _lights(12))  # img0, img1, ..., img11 in that order
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(tmp_path / "cap"), "--store", str(store), "--no-discontinuities"]) == 0
    rgbn = load_rgbn(Store(store), _artifacts(store)[0])
    inner = cv2.erode(surf.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err = np.degrees(np.arccos(np.clip((rgbn.normals * surface_normals(surf)).sum(-1), -1, 1)))
    assert err[inner].mean() < 1.0


def test_a_file_instead_of_a_folder_is_refused(tmp_path, capsys):
    (tmp_path / "x.jpg").write_bytes(b"")
    assert tessera(["import", "rti", str(tmp_path / "x.jpg"), "--store", str(tmp_path / "s")]) == 2
    assert "x.jpg: not a folder" in capsys.readouterr().err
    assert not (tmp_path / "s").exists()


@pytest.mark.data
@pytest.mark.slow
def test_real_rti_captures_import_without_a_mask(shared_data, tmp_path, capsys):
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(shared_data / "realrti-dev"), "--store", str(store),
                    "--no-discontinuities", "--method", "least_squares"]) == 0
    found = _artifacts(store)
    assert [p.split("/")[1] for p in found] == ["item1", "item5", "item8"]
    for rel in found:
        rgbn = load_rgbn(Store(store), rel)
        assert rgbn.mask.mean() > 0.99  # frame-filling: the whole frame is the object


def test_a_capture_without_a_light_file_is_calibrated_from_its_spheres(tmp_path, capsys):
    from common.acquisition.spheres import sphere_normals

    surf = _surface(64)
    pad = ((0, 36), (0, 136))
    wide = FragmentSurface(np.pad(surf.albedo, pad + ((0, 0),)), np.pad(surf.height_mm, pad),
                           np.pad(surf.mask, pad), 254.0)
    lights = _lights(12, seed=7)
    images = simulate_flash_capture(wide, lights)
    mirror, diffuse = (100.0, 50.0, 26.0), (165.0, 48.0, 27.0)
    nm, im = sphere_normals(images.shape[1:3], mirror)
    nd, idf = sphere_normals(images.shape[1:3], diffuse)
    refl = 2 * nm[..., 2:3] * nm - [0, 0, 1]
    cap = tmp_path / "sherd-12"
    cap.mkdir()
    for i, (img, l) in enumerate(zip(images, lights)):
        img[im] = (np.exp(-(np.degrees(np.arccos(np.clip(refl @ l, -1, 1))) / 6) ** 2) + 0.02)[im, None]
        img[idf] = (0.6 * np.clip(nd @ l, 0, None))[idf, None]
        cv2.imwrite(str(cap / f"f{i}.png"), np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)[..., ::-1])
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(cap), "--spheres", "auto", "auto", "--store", str(store),
                    "--no-discontinuities"]) == 0
    found = _artifacts(store)
    assert [p.split("/")[1] for p in found] == ["sherd-12"]
    rgbn = load_rgbn(Store(store), found[0])
    assert not (rgbn.mask & (im | idf)).any()  # the spheres are not part of the fragment
    inner = cv2.erode(wide.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err = np.degrees(np.arccos(np.clip((rgbn.normals * surface_normals(wide)).sum(-1), -1, 1)))
    assert err[inner].mean() < 1.5


def test_a_capture_of_another_bit_depth_than_declared_is_refused(tmp_path, capsys):
    _capture(tmp_path / "cap16")  # 16-bit PNGs
    store = tmp_path / "store"
    assert tessera(["import", "rti", str(tmp_path / "cap16"), "--bit-depth", "8", "--store", str(store)]) == 1
    err = capsys.readouterr().err
    assert "img0.png" in err and "8-bit was declared" in err
    assert _artifacts(store) == []


def test_more_than_two_spheres_are_refused(tmp_path, capsys):
    # docs/handheld.md: --spheres MIRROR [DIFFUSE]; a third spec must not be dropped silently
    _capture(tmp_path / "cap", lp=False)
    assert tessera(["import", "rti", str(tmp_path / "cap"), "--spheres", "auto", "auto", "auto",
                    "--store", str(tmp_path / "store")]) == 2
    assert "--spheres takes MIRROR [DIFFUSE]" in capsys.readouterr().err
    assert _artifacts(tmp_path / "store") == []


def test_the_same_capture_under_a_second_id_is_refused_naming_the_first(tmp_path, capsys):
    """A capture folder copied under another name (or imported again from another collection) made a second
    fragment, proposed as a join to the first: any of its images already imported as another fragment makes it
    that fragment again, refused naming it unless ``--allow-duplicates``. The light file is the dome's, the same
    file for every capture made with it: another capture with the same ``.lp`` is imported."""
    import shutil

    _capture(tmp_path / "a" / "F-A")
    store = tmp_path / "store"
    base = ["--store", str(store), "--no-discontinuities"]
    assert tessera(["import", "rti", str(tmp_path / "a" / "F-A"), *base]) == 0
    shutil.copytree(tmp_path / "a" / "F-A", tmp_path / "b" / "F-A-copy")
    _capture(tmp_path / "b" / "F-C", tilt=-0.2)   # another fragment under the same lights: the same capture.lp
    assert (tmp_path / "b" / "F-C" / "capture.lp").read_bytes() == (tmp_path / "a" / "F-A" / "capture.lp").read_bytes()
    capsys.readouterr()
    assert tessera(["import", "rti", str(tmp_path / "b"), *base]) == 1
    out = capsys.readouterr()
    assert "imported 1, already imported 0, refused 1" in out.out
    assert ("refused F-A-copy: img0.png: the same file (sha256 " in out.err
            and "is already imported as fragment F-A (front, 96 dpi: fragments/F-A/rgbn/front-" in out.err
            and "not imported again as F-A-copy (front): give --allow-duplicates" in out.err), out.err
    assert [p.split("/")[1] for p in _artifacts(store)] == ["F-A", "F-C"]
    assert tessera(["import", "rti", str(tmp_path / "b" / "F-A-copy"), "--allow-duplicates", *base]) == 0
    assert sorted(p.split("/")[1] for p in _artifacts(store)) == ["F-A", "F-A-copy", "F-C"]


def test_the_same_capture_at_another_dpi_is_refused_naming_both_unless_replace(tmp_path, capsys):
    """The same capture imported again for its fragment at another --dpi added a second, rescaled face: refused
    naming both dpi values; ``--replace`` imports it. Found from the face's provenance too (another bench)."""
    _capture(tmp_path / "F-D")
    store = tmp_path / "store"
    base = [str(tmp_path / "F-D"), "--store", str(store), "--no-discontinuities"]
    assert tessera(["import", "rti", *base]) == 0
    (store / "imports" / "ledger.jsonl").unlink()   # as if another bench imported it
    capsys.readouterr()
    assert tessera(["import", "rti", *base, "--dpi", "300"]) == 1
    assert ("refused F-D: img0.png: the same file is already imported for fragment F-D (front) at 96 dpi; this "
            "import gives 300 dpi: give --replace to make the 300 dpi face replace the 96 dpi one"
            ) in capsys.readouterr().err
    assert len(_artifacts(store)) == 1
    assert tessera(["import", "rti", *base, "--dpi", "300", "--replace"]) == 0
    assert len(_artifacts(store)) == 2
