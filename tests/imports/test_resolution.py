"""The dpi a file declares (PNG pHYs, TIFF XResolution/ResolutionUnit, JPEG JFIF) and its use by import scans."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image

from common.imports.resolution import file_dpi


def _png_with_phys(path, ppm_x, ppm_y, unit=1):
    """A PNG written by OpenCV (no pHYs), with a pHYs chunk spliced in before IDAT by hand."""
    ok, buf = cv2.imencode(".png", np.full((8, 8, 3), 100, np.uint8))
    data = buf.tobytes()
    i = data.index(b"IDAT") - 4
    body = struct.pack(">IIB", ppm_x, ppm_y, unit)
    chunk = struct.pack(">I", len(body)) + b"pHYs" + body + struct.pack(">I", zlib.crc32(b"pHYs" + body))
    path.write_bytes(data[:i] + chunk + data[i:])
    return path


def test_png_phys_in_pixels_per_metre(tmp_path):
    # 300 dpi = 11811 pixels per metre (rounded as scanners write it)
    p = _png_with_phys(tmp_path / "a.png", 11811, 11811)
    assert file_dpi(p) == pytest.approx(11811 * 0.0254, abs=1e-9)
    assert file_dpi(p) == pytest.approx(300.0, abs=0.01)


def test_png_without_phys_or_with_an_aspect_ratio_only_declares_nothing(tmp_path):
    p = tmp_path / "plain.png"
    cv2.imwrite(str(p), np.full((8, 8, 3), 100, np.uint8))
    assert file_dpi(p) is None
    assert file_dpi(_png_with_phys(tmp_path / "aspect.png", 1, 1, unit=0)) is None


def test_png_non_square_pixels_are_refused(tmp_path):
    with pytest.raises(ValueError, match="non-square"):
        file_dpi(_png_with_phys(tmp_path / "ns.png", 11811, 23622))


@pytest.mark.parametrize("unit,value,expected", [("inch", 600, 600.0), ("cm", 100, 254.0)])
def test_tiff_resolution_and_unit(tmp_path, unit, value, expected):
    import tifffile
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, np.full((8, 8, 3), 1000, np.uint16), resolution=(value, value),
                     resolutionunit=2 if unit == "inch" else 3)
    assert file_dpi(p) == pytest.approx(expected)


def test_tiff_without_unit_declares_nothing(tmp_path):
    import tifffile
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, np.full((8, 8, 3), 1000, np.uint16), resolution=(300, 300), resolutionunit=1)
    assert file_dpi(p) is None


def test_jpeg_jfif_density(tmp_path):
    p = tmp_path / "j.jpg"
    Image.fromarray(np.full((8, 8, 3), 100, np.uint8)).save(p, dpi=(400, 400))
    assert file_dpi(p) == pytest.approx(400.0)


def _scans(tmp_path, dpi_ppm=None):
    """Four small turned scans of a painted square on a dark bed (enough to register)."""
    rng = np.random.default_rng(0)
    paths = []
    base = np.zeros((120, 120, 3), np.uint8) + 30
    tex = (rng.random((50, 50, 3)) * 120 + 100).astype(np.uint8)
    tex = cv2.GaussianBlur(tex, (0, 0), 1.5)
    for k in range(4):
        s = base.copy()
        s[35:85, 35:85] = np.rot90(tex, -k)
        p = tmp_path / f"s{k}.png"
        if dpi_ppm:
            ok, buf = cv2.imencode(".png", s[..., ::-1])
            data = buf.tobytes()
            i = data.index(b"IDAT") - 4
            body = struct.pack(">IIB", dpi_ppm, dpi_ppm, 1)
            chunk = struct.pack(">I", len(body)) + b"pHYs" + body + struct.pack(">I", zlib.crc32(b"pHYs" + body))
            p.write_bytes(data[:i] + chunk + data[i:])
        else:
            cv2.imwrite(str(p), s[..., ::-1])
        paths.append(p)
    return paths


def test_import_scans_without_dpi_is_refused_when_the_files_declare_none(tmp_path, capsys):
    from services.cli import main
    paths = _scans(tmp_path)
    rc = main(["import", "scans", *map(str, paths), "--fragment", "F1", "--device", "d", "--store",
               str(tmp_path / "store")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "no dpi" in err and "--dpi" in err
    assert not (tmp_path / "store" / "fragments").exists()


def test_import_scans_reads_the_dpi_from_the_files_and_warns_on_a_mismatch(tmp_path, capsys):
    from services.cli import main
    from services.cli.import_scans import _dpi_of
    paths = _scans(tmp_path, dpi_ppm=5906)          # 150.0 dpi
    g = {"front": paths, "back": [], "dpi": None, "where": "arguments"}
    assert _dpi_of("F1", g) == pytest.approx(150.01, abs=0.01)
    g["dpi"] = 300.0
    assert _dpi_of("F1", g) == 300.0
    assert "declares 150 dpi but 300 dpi was given" in capsys.readouterr().err
    g["dpi"] = 150.0
    assert _dpi_of("F1", g) == 150.0
    assert "declares" not in capsys.readouterr().err


def test_import_scans_uses_a_manifest_dpi_given_on_any_row_of_the_fragment(tmp_path, capsys):
    # docs/flatbed.md: the files' dpi counts only "without --dpi or a dpi column"; a dpi cell left
    # empty on the first row must not make the column's 300 dpi give way to the files' 150
    from common.acquisition.capture import read_scans
    from common.store import Store
    from services.cli import main
    paths = _scans(tmp_path, dpi_ppm=5906)          # the files declare 150 dpi
    rows = "".join(f"{p.name},F1,{'' if k == 0 else 300}\n" for k, p in enumerate(paths))
    (tmp_path / "scans.csv").write_text("file,fragment,dpi\n" + rows)
    assert main(["import", "scans", "--manifest", str(tmp_path / "scans.csv"), "--device", "d",
                 "--store", str(tmp_path / "store")]) == 0
    assert "declares 150 dpi but 300 dpi was given" in capsys.readouterr().err
    store = Store(tmp_path / "store")
    [f] = (tmp_path / "store" / "fragments").rglob("scans-*.h5")
    capture = read_scans(store, store.ref(f.relative_to(tmp_path / "store").as_posix()))
    assert [s.dpi for s in capture.scans["front"]] == [300.0] * 4
