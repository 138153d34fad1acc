import numpy as np
import pytest

from common.synth.stats import Piece, comparison_table, neighbour_gaps, piece_statistics, read_collection


def _rect_piece(name, obj, h, w, x, y):
    rgba = np.zeros((h, w, 4), np.uint8)
    rgba[...] = (170, 166, 160, 255)
    return Piece(name, obj, rgba, np.array([[1.0, 0, x], [0, 1.0, y]]))


@pytest.mark.parametrize("gap", [0, 3, 12, 30])
def test_neighbour_gaps_measure_the_gap_between_placed_pieces(gap):
    a = _rect_piece("a", "o", 300, 100, 0, 0)
    b = _rect_piece("b", "o", 300, 100, 100 + gap, 0)
    far = _rect_piece("c", "o", 300, 100, 400, 0)
    corner = _rect_piece("d", "o", 100, 100, 100 + gap, 300 + gap)  # meets a at a corner only
    other = _rect_piece("e", "p", 300, 100, 100 + gap, 0)  # another object at b's place
    pairs = neighbour_gaps([a, b, far, corner, other], near_px=48, min_run_px=100)
    found = {(p["a"], p["b"]): p for p in pairs}
    assert ("a", "b") in found and ("a", "c") not in found and ("a", "e") not in found
    assert ("a", "d") not in found  # a corner contact is shorter than 100 px
    assert found[("a", "b")]["min_gap_px"] == pytest.approx(gap, abs=0.6)
    assert found[("a", "b")]["run_px"] >= 300


def _disc_rgba(r_px, size, colour=(170, 166, 160)):
    yy, xx = np.mgrid[0:size, 0:size]
    m = (yy - size / 2) ** 2 + (xx - size / 2) ** 2 < r_px ** 2
    rgba = np.zeros((size, size, 4), np.uint8)
    rgba[m] = colour + (255,)
    return rgba, m


def test_piece_statistics_of_a_disc_match_geometry():
    rgba, _ = _disc_rgba(200, 440)  # 20 mm radius at 254 dpi (0.1 mm/px)
    s = piece_statistics(rgba, 254.0)
    assert s["size_mm"] == pytest.approx(np.sqrt(np.pi) * 20, rel=0.01)
    assert s["diameter_mm"] == pytest.approx(40, rel=0.01)
    # a circle turns by arc / radius over every chord: 10 mm -> 0.5 rad
    assert s["turn10_deg"] == pytest.approx(np.degrees(0.5), rel=0.05)
    assert s["rough_mm"] < 0.12 and s["plain_edge"] == 1.0 and s["painted"] == 0.0


def test_piece_statistics_see_roughness_and_paint_at_the_edge():
    size, R = 440, 200
    yy, xx = np.mgrid[0:size, 0:size]
    th = np.arctan2(yy - size / 2, xx - size / 2)
    # a 0.4 mm (4 px) sinusoidal jag of 2 mm wavelength along the rim (63 periods)
    m = np.hypot(yy - size / 2, xx - size / 2) < R + 4 * np.sin(63 * th)
    rgba = np.zeros((size, size, 4), np.uint8)
    rgba[m] = (170, 166, 160, 255)
    # red paint along the right half of the edge band
    ring = m & (np.hypot(yy - size / 2, xx - size / 2) > R - 40) & (xx > size / 2)
    rgba[ring, :3] = (190, 90, 80)
    s = piece_statistics(rgba, 254.0)
    assert 0.2 < s["rough_mm"] < 0.4  # rms of a 0.4 mm sinusoid is 0.28 mm
    assert s["plain_edge"] == pytest.approx(0.5, abs=0.06)
    assert s["C_p90"] > 15


def test_real_collection_statistics_when_the_repair_set_is_present():
    from pathlib import Path

    from common.synth.stats import REPAIR_DPI, collection_statistics
    root = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "repair-dev"
    if not root.is_dir():
        pytest.skip(f"RePAIR development set not found at {root}")
    pieces = [p for p in read_collection(root) if p.object in ("RPobj_g13_o0013", "RPobj_g14_o0014")]
    s = collection_statistics(pieces, REPAIR_DPI)
    # what the data set's README states: true neighbours rarely touch, mostly plain plaster
    assert s["n_pairs"] >= 5
    assert s["min_gap_mm"][1] > 0.2 and s["median_gap_mm"][1] > 1.0
    assert s["plain_edge_all"] > 0.7
    table = comparison_table({"real": s})
    assert "| smallest gap per pair, mm" in table and table.count("\n") > 15


def _collection_with_truth(root, truth_text):
    import cv2

    obj = root / "objA"
    obj.mkdir(parents=True)
    rgba = np.zeros((20, 30, 4), np.uint8)
    rgba[4:16, 5:25] = (160, 150, 140, 255)
    for name in ("p1", "p2"):
        cv2.imwrite(str(obj / f"{name}.png"), rgba)
    (obj / "truth.csv").write_text(truth_text)
    return obj


def test_truth_rows_may_name_a_fragment_by_file_name_or_stem(tmp_path):
    _collection_with_truth(tmp_path, "rpf,x,y,rot\np1.png,10,20,0\np2,40,20,90\n")
    placed = {p.id: p.matrix for p in read_collection(tmp_path)}
    assert placed["p1"] is not None and placed["p2"] is not None
    # p1: not turned, its crop's corner (col 3, row 2 after the 2-px pad) lands at (10 + 3, 20 + 2)
    assert np.allclose(placed["p1"] @ [0, 0, 1], [13, 22])


@pytest.mark.parametrize("text, words", [
    ("rpf,x,y\np1.png,1,2\n", ["truth.csv", "missing column", "rot"]),
    ("rpf,x,y,rot\np1.png,abc,2,0\n", ["truth.csv, line 2", "numbers", "'abc'"]),
    ("rpf,x,y,rot\np1.png,1,2,0\np9.png,1,2,0\n", ["truth.csv, line 3", "'p9.png'", "names no fragment image"]),
    ("rpf,x,y,rot\np1.png,1,2,0\np1,5,2,0\n", ["line 3", "p1.png is placed twice"]),
    ("rpf,x,y,rot\np1.png,1,nan,0\n", ["line 2", "finite"]),
])
def test_a_bad_truth_file_is_refused_naming_the_file_line_and_problem(tmp_path, text, words):
    _collection_with_truth(tmp_path, text)
    with pytest.raises(ValueError) as err:
        read_collection(tmp_path)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def _spoil_truncate(png):
    png.write_bytes(png.read_bytes()[:-40])   # cuts into the last IDAT chunk and drops IEND


def _spoil_no_alpha(png):
    import cv2

    cv2.imwrite(str(png), np.full((20, 30, 3), 150, np.uint8))


def _spoil_transparent(png):
    import cv2

    cv2.imwrite(str(png), np.zeros((20, 30, 4), np.uint8))


@pytest.mark.parametrize("spoil, words", [
    (_spoil_truncate, ["p2.png", "truncated"]),
    (_spoil_no_alpha, ["p2.png", "blank"]),   # RGB without alpha and nothing on its background
    (_spoil_transparent, ["p2.png", "fully transparent"]),
])
def test_a_damaged_fragment_image_is_refused_naming_the_file_and_problem(tmp_path, spoil, words):
    # OpenCV alone decodes a truncated PNG with its missing rows grey: the piece would be imported
    # with a false outline
    obj = _collection_with_truth(tmp_path, "rpf,x,y,rot\np1.png,10,20,0\n")
    spoil(obj / "p2.png")
    with pytest.raises(ValueError) as err:
        read_collection(tmp_path)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_an_rgb_fragment_image_on_a_plain_background_reads_as_the_same_piece_and_placement(tmp_path):
    # a piece photographed on black: its alpha comes from the background, so the crop and the placed
    # matrix are those of the RGBA file it was made from
    import cv2

    obj = _collection_with_truth(tmp_path, "rpf,x,y,rot\np1.png,10,20,30\n")
    rgba = {p.id: p for p in read_collection(tmp_path)}["p1"]
    canvas = np.zeros((20, 30, 3), np.uint8)
    canvas[4:16, 5:25] = (160, 150, 140)
    cv2.imwrite(str(obj / "p1.png"), canvas)
    rgb = {p.id: p for p in read_collection(tmp_path)}["p1"]
    assert rgb.rgba.shape == rgba.rgba.shape and np.array_equal(rgb.rgba, rgba.rgba)
    assert np.allclose(rgb.matrix, rgba.matrix)


def test_a_16_bit_fragment_image_reads_as_its_8_bit_values(tmp_path):
    import cv2

    obj = _collection_with_truth(tmp_path, "rpf,x,y,rot\n")
    eight = {p.id: p.rgba for p in read_collection(tmp_path)}["p1"]
    rgba16 = np.zeros((20, 30, 4), np.uint16)
    rgba16[4:16, 5:25] = np.array((160, 150, 140, 255), np.uint16) * 257
    cv2.imwrite(str(obj / "p1.png"), rgba16)
    sixteen = {p.id: p.rgba for p in read_collection(tmp_path)}["p1"]
    assert sixteen.dtype == np.uint8 and np.array_equal(sixteen, eight)


def test_every_damaged_fragment_image_is_named_at_once(tmp_path):
    obj = _collection_with_truth(tmp_path, "rpf,x,y,rot\n")
    _spoil_truncate(obj / "p1.png")
    _spoil_transparent(obj / "p2.png")
    with pytest.raises(ValueError) as err:
        read_collection(tmp_path)
    text = str(err.value)
    assert text.startswith("2 fragment image(s) refused") and "p1.png" in text and "p2.png" in text, text


def test_a_collection_of_jpeg_and_tiff_pictures_reads_like_png(tmp_path):
    # a lab's photographs are often JPEG or TIFF: the collection reads what `tessera import images` reads,
    # truth rows naming a picture by its stem whatever its suffix
    import cv2

    obj = tmp_path / "objA"
    obj.mkdir()
    canvas = np.zeros((40, 60, 3), np.uint8)
    canvas[8:32, 10:50] = (160, 150, 140)
    cv2.imwrite(str(obj / "p1.jpg"), canvas, [cv2.IMWRITE_JPEG_QUALITY, 95])
    cv2.imwrite(str(obj / "p2.TIF"), canvas)
    (obj / "notes.txt").write_text("not a picture")
    (obj / "truth.csv").write_text("rpf,x,y,rot\np1,10,20,0\np2.TIF,40,20,90\n")
    pieces = {p.id: p for p in read_collection(tmp_path)}
    assert set(pieces) == {"p1", "p2"} and all(p.matrix is not None for p in pieces.values())
    for p in pieces.values():      # the piece, 24 x 40 px, found on its black background
        assert abs(int((p.rgba[..., 3] > 0).sum()) - 24 * 40) < 40
    cv2.imwrite(str(obj / "p1.png"), canvas)    # p1.jpg and p1.png: "p1" names neither alone
    with pytest.raises(ValueError, match="'p1' could be any of p1.jpg, p1.png"):
        read_collection(tmp_path)
