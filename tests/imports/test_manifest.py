"""Manifests, fragment ids and folder expansion."""

from __future__ import annotations

import pytest

from common.imports.manifest import expand_paths, fragment_id, natural_key, read_manifest


def test_natural_order_puts_2_before_10(tmp_path):
    for n in (1, 10, 11, 2, 3):
        (tmp_path / f"img{n}.png").write_bytes(b"x")
    (tmp_path / "notes.txt").write_text("not a picture")
    (tmp_path / ".hidden.png").write_bytes(b"x")
    assert [p.name for p in expand_paths([tmp_path])] == ["img1.png", "img2.png", "img3.png", "img10.png", "img11.png"]
    assert sorted(["a10", "a9"], key=natural_key) == ["a9", "a10"]
    assert expand_paths([tmp_path / "missing.png"]) == [tmp_path / "missing.png"]   # refused later, by name


@pytest.mark.parametrize("text,expected", [("Inv. 1998/12", "Inv.-1998-12"), ("  F0042 ", "F0042"),
                                           ("_x y", "x-y"), ("Sala 4 – n° 7", "Sala-4-n-7")])
def test_fragment_id_from_inventory_numbers(text, expected):
    assert fragment_id(text) == expected


def test_fragment_id_needs_letters_or_digits():
    with pytest.raises(ValueError, match="cannot make a fragment id"):
        fragment_id(" // ")
    assert len(fragment_id("x" * 100)) == 64


def test_manifest_columns_are_normalised_and_files_resolved(tmp_path):
    (tmp_path / "m.csv").write_text("\ufeffFile,Inventory No,Find-Spot,Context,Date,Notes,Colour\n"
                                    "a.png,12,Room 1,US 5,1999,\"burnt, cracked\",red\n\n"
                                    "sub/b.png,13,,,,,\n", encoding="utf-8")
    rows = read_manifest(tmp_path / "m.csv")
    assert rows[0] == {"file": str((tmp_path / "a.png").resolve()), "inventory": "12", "find_spot": "Room 1",
                       "context": "US 5", "date": "1999", "notes": "burnt, cracked", "colour": "red", "line": 2}
    assert rows[1] == {"file": str((tmp_path / "sub" / "b.png").resolve()), "inventory": "13", "line": 4}


def test_bad_manifests_are_refused_naming_the_file_and_line(tmp_path):
    (tmp_path / "nofile.csv").write_text("inventory,notes\n1,x\n")
    with pytest.raises(ValueError, match="nofile.csv has no 'file' column"):
        read_manifest(tmp_path / "nofile.csv")
    (tmp_path / "long.csv").write_text("file,notes\na.png,x,y\n")
    with pytest.raises(ValueError, match="long.csv line 2 has 3 cells"):
        read_manifest(tmp_path / "long.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(ValueError, match="empty.csv is empty"):
        read_manifest(tmp_path / "empty.csv")
    with pytest.raises(ValueError, match="gone.csv cannot be read"):
        read_manifest(tmp_path / "gone.csv")


def test_column_names_match_without_case_spaces_or_hyphens(tmp_path):
    # docs/import.md: "column names are matched ignoring case, spaces and hyphens" -- an export that
    # wrote "InventoryNumber" or "FIND SPOT" names the same columns as "inventory number", "find_spot"
    (tmp_path / "m.tsv").write_text("FILE\tInventoryNumber\tFindSpot\tFace\n"
                                    "a.png\tInv. 7\tRoom 2\tBack\n", encoding="utf-8")
    (tmp_path / "m.csv").write_text("file,INV-NO,Find Spot\na.png,Inv. 7,Room 2\n", encoding="utf-8")
    tab, comma = read_manifest(tmp_path / "m.tsv")[0], read_manifest(tmp_path / "m.csv")[0]
    assert tab["inventory"] == comma["inventory"] == "Inv. 7"
    assert tab["find_spot"] == comma["find_spot"] == "Room 2"
    assert tab["face"] == "Back"
