"""Reading a placed collection made elsewhere (``tessera evaluate --collection``): layouts and files that other
tools write (spreadsheet CSVs, other picture formats, stray files) read as the plain ``repair-dev`` layout does;
a bad piece is named with its file and reason, and in the evaluation's reading it is left out with that reason
while the rest goes on. Tiny synthetic pictures written to tmp_path; common/synth/stats.py,
common/matching/collection.py and services/cli/evaluate.py."""

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.synth.stats import read_collection

PLAIN = "rpf,x,y,rot\np1.png,10,20,0\np2.png,40,20.5,90\n"


def _piece(h=20, w=30, colour=(160, 150, 140)):
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[4:h - 4, 5:w - 5] = (*colour, 255)
    return rgba


def _object(root, truth=PLAIN, name="objA", pieces=("p1", "p2")):
    obj = Path(root) / name
    obj.mkdir(parents=True, exist_ok=True)
    for p in pieces:
        cv2.imwrite(str(obj / f"{p}.png"), _piece())
    if truth is not None:
        (obj / "truth.csv").write_bytes(truth if isinstance(truth, bytes) else truth.encode())
    return obj


def _placed(root, **kw):
    return {p.id: p.matrix for p in read_collection(root, **kw)}


# ------------------------------------------------------------------------ truth.csv as other tools write it
@pytest.mark.parametrize("name, truth", [
    ("UTF-8 BOM (Excel's 'CSV UTF-8')", b"\xef\xbb\xbf" + PLAIN.encode()),
    ("BOM and Windows line endings", b"\xef\xbb\xbf" + PLAIN.replace("\n", "\r\n").encode()),
    ("spaces around names and values", "rpf , x, y , rot\n  p1.png , 10 ,20, 0\np2.png,  40,20.5 ,90  \n\n  \n"),
    ("upper-case header", PLAIN.replace("rpf,x,y,rot", "RPF,X,Y,Rot")),
    ("semicolons and decimal commas (a European spreadsheet)", "rpf;x;y;rot\np1.png;10;20;0\np2.png;40;20,5;90\n"),
    ("tab-separated", PLAIN.replace(",", "\t")),
    ("empty cells and rows of commas (a spreadsheet's export)", PLAIN.replace("\n", ",,\n") + ",,,,\n,,,,\n"),
    ("UTF-16 with BOM (Excel's 'Unicode text')", PLAIN.encode("utf-16")),
    ("names with a folder path",
     PLAIN.replace("p1.png", "C:\\scans\\objA\\p1.png").replace("p2.png", "scans/objA/p2.png")),
    ("names as stems or another case of the suffix", PLAIN.replace("p1.png", "p1").replace("p2.png", "p2.PNG")),
])
def test_a_truth_file_written_by_another_tool_places_the_pieces_as_the_plain_one(tmp_path, name, truth):
    _object(tmp_path / "plain")
    _object(tmp_path / "other", truth=truth)
    want, got = _placed(tmp_path / "plain"), _placed(tmp_path / "other")
    assert set(got) == set(want) == {"p1", "p2"}
    for k in want:
        assert got[k] is not None and np.allclose(got[k], want[k]), (name, k)


def test_a_windows_1252_truth_file_names_accented_pictures(tmp_path):
    # Excel's plain "CSV" on Windows writes the code page, not UTF-8
    _object(tmp_path / "plain", truth=PLAIN.replace("p1", "città1"), pieces=("città1", "p2"))
    _object(tmp_path / "other", truth=PLAIN.replace("p1", "città1").encode("cp1252"), pieces=("città1", "p2"))
    want, got = _placed(tmp_path / "plain"), _placed(tmp_path / "other")
    assert set(got) == {"città1", "p2"} and all(got[k] is not None and np.allclose(got[k], want[k]) for k in want)


def test_a_truth_file_name_in_another_case_is_read(tmp_path):
    _object(tmp_path / "plain")
    (_object(tmp_path / "other") / "truth.csv").rename(tmp_path / "other" / "objA" / "Truth.CSV")
    want, got = _placed(tmp_path / "plain"), _placed(tmp_path / "other")
    assert all(got[k] is not None and np.allclose(got[k], want[k]) for k in want)


def test_a_row_naming_the_picture_in_another_format_finds_it(tmp_path):
    # a collection converted from PNG to TIFF (or JPEG) keeps its truth.csv
    _object(tmp_path / "plain")
    obj = _object(tmp_path / "other")
    for p in ("p1", "p2"):
        cv2.imwrite(str(obj / f"{p}.tif"), cv2.imread(str(obj / f"{p}.png"), cv2.IMREAD_UNCHANGED))
        (obj / f"{p}.png").unlink()
    want, got = _placed(tmp_path / "plain"), _placed(tmp_path / "other")
    assert all(got[k] is not None and np.allclose(got[k], want[k]) for k in want)


def test_a_truth_file_that_cannot_be_decoded_is_named(tmp_path):
    _object(tmp_path, truth=b"\xff\xfe\x00")    # a UTF-16 BOM and half a character
    with pytest.raises(ValueError, match=r"truth\.csv: .*(decode|text)"):
        read_collection(tmp_path)


def test_a_missing_column_is_named_with_the_columns_found(tmp_path):
    _object(tmp_path, truth="file,x,y,angle\np1.png,1,2,0\n")
    with pytest.raises(ValueError, match=r"truth\.csv: missing column\(s\) rpf, rot .*found: file, x, y, angle"):
        read_collection(tmp_path)


# ------------------------------------------------------------------------------ pictures as other tools write them
def test_rgba_with_an_alpha_that_hides_nothing_is_cut_from_its_background(tmp_path):
    # some tools write RGBA with alpha 255 everywhere, the piece on black: read as RGB on its background,
    # not as a piece the size of the whole canvas
    obj = _object(tmp_path)
    rgb = _piece()[..., :3]
    cv2.imwrite(str(obj / "p1.png"), np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]))
    piece = {p.id: p for p in read_collection(tmp_path)}["p1"]
    assert (piece.rgba[..., 3] > 0).sum() == 12 * 20


@pytest.mark.parametrize("mode", ["L", "LA"])
def test_a_grey_picture_reads_as_its_grey_piece(tmp_path, mode):
    from PIL import Image

    obj = _object(tmp_path)
    grey = _piece(colour=(150, 150, 150))
    grey[6:14, 8:22, :3] = 90                  # a painted patch: a uniform piece is refused as blank
    im = Image.fromarray(grey[..., 0]) if mode == "L" else Image.fromarray(grey[..., [0, 3]].copy(), "LA")
    (obj / "p1.png").unlink()
    im.save(obj / "p1.tif")
    piece = {p.id: p for p in read_collection(tmp_path)}["p1"]
    assert piece.rgba.shape[2] == 4 and (piece.rgba[..., 3] > 0).sum() == 12 * 20
    inside = piece.rgba[piece.rgba[..., 3] == 255]
    assert set(np.unique(inside[:, :3])) == {90, 150}


def test_two_pictures_of_one_stem_in_an_object_keep_apart(tmp_path):
    obj = _object(tmp_path, truth="rpf,x,y,rot\np1.png,10,20,0\np1.tif,40,20,0\np2.png,0,0,0\n")
    cv2.imwrite(str(obj / "p1.tif"), _piece())
    pieces = read_collection(tmp_path)
    ids = [p.id for p in pieces]
    assert len(set(ids)) == len(ids) == 3 and {"p1.png", "p1.tif", "p2"} == set(ids)


# ------------------------------------------------------------------------------------------- the folder layout
def test_hidden_folders_and_stray_files_are_not_read(tmp_path):
    obj = _object(tmp_path)
    for junk in (".DS_Store", "Thumbs.db", "README.txt", "._p1.png"):
        (obj / junk).write_bytes(b"\x00\x05\x16\x07 not a picture")
    (tmp_path / ".DS_Store").write_bytes(b"\x00\x00")
    for hidden in (".thumbnails", "__MACOSX"):
        (tmp_path / hidden).mkdir()
        (tmp_path / hidden / "p9.png").write_bytes(b"\x00\x05\x16\x07 not a picture")
    assert set(_placed(tmp_path)) == {"p1", "p2"}


def test_what_the_layout_leaves_out_is_said(tmp_path, caplog):
    _object(tmp_path)
    (tmp_path / "empty").mkdir()
    cv2.imwrite(str(tmp_path / "stray.png"), _piece())
    skipped = []
    with caplog.at_level(logging.WARNING, logger="tessera.collection"):
        assert set(_placed(tmp_path, skipped=skipped)) == {"p1", "p2"}
    text = "\n".join(skipped)
    assert "empty" in text and "no fragment picture" in text
    assert "stray.png" in text and "no object folder" in text
    assert "stray.png" in caplog.text     # logged as well


def test_pictures_directly_in_the_collection_folder_are_refused_saying_the_layout(tmp_path):
    for p in ("p1", "p2"):
        cv2.imwrite(str(tmp_path / f"{p}.png"), _piece())
    (tmp_path / "truth.csv").write_text(PLAIN)
    with pytest.raises(ValueError, match=r"2 fragment pictures directly.*one folder per object"):
        read_collection(tmp_path)


def test_a_collection_nested_one_level_deeper_is_refused_naming_the_folder_to_give(tmp_path):
    _object(tmp_path / "site")
    with pytest.raises(ValueError, match=r"site.* holds object folders.*give .*site"):
        read_collection(tmp_path)


# ------------------------------------------------------------------- the evaluation's reading: skip and go on
def _spoil_truncate(png):
    png.write_bytes(png.read_bytes()[:-40])


@pytest.mark.parametrize("spoil, truth, words", [
    ("truncated", PLAIN + "p3.png,70,20,0\n", ["p3.png", "truncated", "left out"]),
    ("transparent", PLAIN + "p3.png,70,20,0\n", ["p3.png", "fully transparent", "left out"]),
    ("none", PLAIN + "p3.png,70,20,0\np9.png,1,1,0\n", ["truth.csv, line 5", "'p9.png'", "names no fragment image",
                                                          "row ignored"]),
    ("none", PLAIN + "p3.png,n/a,20,0\n", ["truth.csv, line 4", "numbers", "'n/a'", "p3.png", "row ignored"]),
    ("none", PLAIN + "p3.png,70,20,0\np3,71,20,0\n", ["line 5", "p3.png is placed twice", "row ignored"]),
])
def test_the_lenient_reading_leaves_out_a_bad_piece_or_row_naming_it_and_reads_the_rest(tmp_path, spoil, truth, words):
    obj = _object(tmp_path, truth=truth, pieces=("p1", "p2", "p3"))
    if spoil == "truncated":
        _spoil_truncate(obj / "p3.png")
    elif spoil == "transparent":
        cv2.imwrite(str(obj / "p3.png"), np.zeros((20, 30, 4), np.uint8))
    with pytest.raises(ValueError):            # the plain reading refuses
        read_collection(tmp_path)
    skipped = []
    placed = _placed(tmp_path, skipped=skipped)
    assert placed["p1"] is not None and placed["p2"] is not None
    if "p9.png" not in truth:
        assert placed.get("p3") is None        # left out, or with no usable place
    text = "\n".join(skipped)
    for w in words:
        assert w in text, (w, text)


@pytest.mark.parametrize("truth, reason", [
    ("file,x,y,angle\np1.png,1,2,0\n", "missing column"),
    # its pieces are each other's true joins: read as distractors they would count as wrong matches
    ("rpf,x,y,rot\np1.png,n/a,1,0\np2.png,1,,0\n", "none of its rows is usable"),
])
def test_an_object_whose_truth_file_is_unusable_is_left_out_and_the_others_read(tmp_path, truth, reason):
    _object(tmp_path, truth=truth, name="objB")
    _object(tmp_path, name="objA")
    skipped = []
    pieces = read_collection(tmp_path, skipped=skipped)
    assert {p.object for p in pieces} == {"objA"}
    assert any("objB" in s and reason in s and "left out" in s for s in skipped), skipped


def _wall(root, **kw):
    from common.matching.collection import collection_wall

    return collection_wall(root, dpi=30, near_px=5, min_run_px=5, **kw)


def _touching_object(root, name="objA", truth="rpf,x,y,rot\np1.png,0,0,0\np2.png,20,0,0\n", pieces=("p1", "p2")):
    # two 20 x 12 px pieces side by side (each on a 30 x 20 canvas, 5 px margin): neighbours
    return _object(root, truth=truth, name=name, pieces=pieces)


def test_the_evaluation_leaves_out_a_piece_of_a_placed_object_whose_place_is_unknown(tmp_path, caplog):
    # a picture of a placed object without a row would count as a distractor of its own object, its true
    # joins as wrong matches: it is left out, and said so; an object without placement stays a distractor
    _touching_object(tmp_path, pieces=("p1", "p2", "p3"))
    _object(tmp_path, truth=None, name="distractor", pieces=("d1",))
    _object(tmp_path, truth="rpf,x,y,rot\n", name="headeronly", pieces=("h1",))
    with caplog.at_level(logging.WARNING, logger="tessera.collection"):
        wall = _wall(tmp_path)
    ids = {f.id for f in wall.fragments}
    assert ids == {"p1", "p2", "d1", "h1"}
    assert {f.id for f in wall.fragments if f.spurious} == {"d1", "h1"}
    assert len(wall.adjacency) == 1
    text = "\n".join(wall.params["skipped"])
    assert "p3.png" in text and "no row" in text and "left out" in text
    assert "headeronly" in text and "places none" in text
    assert "p3.png" in caplog.text


def test_the_evaluation_reading_goes_on_past_a_damaged_picture(tmp_path):
    obj = _touching_object(tmp_path, truth="rpf,x,y,rot\np1.png,0,0,0\np2.png,20,0,0\np3.png,40,0,0\n",
                           pieces=("p1", "p2", "p3"))
    _spoil_truncate(obj / "p3.png")
    wall = _wall(tmp_path)
    assert {f.id for f in wall.fragments} == {"p1", "p2"} and len(wall.adjacency) == 1
    assert any("p3.png" in s and "truncated" in s for s in wall.params["skipped"])
    with pytest.raises(ValueError, match="p3.png.*truncated"):
        _wall(tmp_path, strict=True)


# ------------------------------------------------------------------------------------------------- the command
def _fake_result(path, dpi):
    k3, k2 = {1: 0.5, 5: 1.0, 10: 1.0}, {1: 0.5, 3: 1.0}
    return {"collection": str(path), "n_fragments": 2, "n_true_pairs": 1, "dpi": dpi, "model": "m",
            "single_fresco": False, "pooled_topk": k3, "pooled_topk_by_probability": k3,
            "within_object_recall": k2, "within_object_random": k2, "within_object_incidence": k2,
            "within_object_recall_by_query": k2, "wrong_pose_scores_above_truth": 0, "pair_ap": 1.0,
            "pair_ap_by_probability": 1.0, "pose_accuracy": 0.0, "pose_offered": 0.0, "pose_reachable": 0.0,
            "seconds": 0.0,
            "cpu_seconds": 0.0, "intervals": {"level": 0.9, "pooled_topk": {k: (0, 1) for k in k3},
                                              "within_object_recall": {k: (0, 1) for k in k2},
                                              "pose_accuracy": (0, 1), "pose_offered": (0, 1),
                                              "pose_reachable": (0, 1)}}


@pytest.fixture
def fake_evaluation(monkeypatch):
    """``evaluate_collection`` reduced to its reading of the collection (what the command reports on)."""
    import common.matching.report as report

    calls = []

    def fake(path, *, dpi=150.0, **kw):
        from common.matching.collection import collection_wall

        calls.append(path)
        wall = collection_wall(path, dpi=dpi)
        return dict(_fake_result(path, dpi), skipped=wall.params["skipped"])

    monkeypatch.setattr(report, "evaluate_collection", fake)
    return calls


def test_the_command_says_what_it_left_out_and_writes_it_to_the_json(tmp_path, capsys, fake_evaluation):
    from services.cli import main

    obj = _touching_object(tmp_path / "c", pieces=("p1", "p2", "p3"),
                           truth="rpf,x,y,rot\np1.png,0,0,0\np2.png,20,0,0\np3.png,40,0,0\n")
    _spoil_truncate(obj / "p3.png")
    assert main(["evaluate", "--collection", str(tmp_path / "c"), "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "left out 1" in out and "p3.png" in out and "truncated" in out
    saved = json.loads((tmp_path / "r.json").read_text())
    assert len(saved["skipped"]) == 1 and "p3.png" in saved["skipped"][0]


@pytest.mark.parametrize("case, words", [
    ("file", ["is a file, not a directory"]),
    ("nothing placed", ["no object folder places two or more", "objA", "no truth.csv"]),
    ("one placed", ["no object folder places two or more", "objA", "1 placed"]),
    ("json is a folder", ["--json", "is a directory"]),
])
def test_the_command_refuses_what_cannot_be_evaluated_before_any_work(tmp_path, fake_evaluation, case, words):
    from services.cli import main

    argv = ["evaluate", "--collection", str(tmp_path / "c")]
    if case == "file":
        (tmp_path / "c").write_text("x")
    elif case == "nothing placed":
        _object(tmp_path / "c", truth=None)
    elif case == "one placed":
        _object(tmp_path / "c", truth="rpf,x,y,rot\np1.png,0,0,0\n")
    else:
        _touching_object(tmp_path / "c")
        (tmp_path / "out").mkdir()
        argv += ["--json", str(tmp_path / "out")]
    with pytest.raises(SystemExit) as err:
        main(argv)
    for w in words:
        assert w in str(err.value), (w, str(err.value))
    assert fake_evaluation == []


def test_the_command_refuses_a_dpi_that_is_not_finite(tmp_path, fake_evaluation):
    from services.cli import main

    _touching_object(tmp_path / "c")
    with pytest.raises(SystemExit, match="--dpi must be a positive number"):
        main(["evaluate", "--collection", str(tmp_path / "c"), "--dpi", "inf"])


def test_the_command_ranks_with_the_fresco_weight_given_and_refuses_a_bad_one(tmp_path, monkeypatch, capsys):
    """--fresco-weight reaches the evaluation (as a station's [services.matcher] fresco_weight would) and is said on
    the first line; a weight that is not a number >= 0 is refused before any work."""
    import common.matching.report as report
    from services.cli import main

    _touching_object(tmp_path / "c")
    got = []

    def fake(path, *, dpi=150.0, fresco_weight=None, **kw):
        got.append(fresco_weight)
        return dict(_fake_result(path, dpi), skipped=[])

    monkeypatch.setattr(report, "evaluate_collection", fake)
    assert main(["evaluate", "--collection", str(tmp_path / "c"), "--fresco-weight", "4"]) == 0
    assert got == [4.0] and "same-fresco ratio weight 4" in capsys.readouterr().out
    for bad in ("-1", "nan"):
        with pytest.raises(SystemExit, match="--fresco-weight must be a number >= 0"):
            main(["evaluate", "--collection", str(tmp_path / "c"), "--fresco-weight", bad])
    assert got == [4.0]
