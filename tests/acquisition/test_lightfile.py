"""Tests of common/acquisition/lightfile.py: .lp and plain light files."""

import numpy as np
import pytest

from common.acquisition.lightfile import LightSet, read_directions, read_intensities, read_lights, read_lp, write_lp


def test_lp_file_gives_unit_directions_and_filenames(tmp_path):
    p = tmp_path / "capture.lp"
    p.write_text("3\nIMG_0001.JPG 0 0 2\nIMG 0002.JPG 3 0 4\nC:\\rti\\jpeg-exports\\IMG_0003.JPG -0.6 0.0 0.8\n")
    lights = read_lp(p)
    np.testing.assert_allclose(lights.directions, [[0, 0, 1], [0.6, 0, 0.8], [-0.6, 0, 0.8]])
    assert lights.filenames[1] == "IMG 0002.JPG"
    # images are matched by file name, whatever order and folder they come in
    order = lights.order_for(["/data/IMG_0003.JPG", "img_0001.jpg", "x/IMG 0002.JPG"])
    assert order.tolist() == [2, 0, 1]


def test_lp_count_disagreeing_with_lines_is_refused(tmp_path):
    p = tmp_path / "bad.lp"
    p.write_text("4\na.jpg 0 0 1\nb.jpg 0 1 1\nc.jpg 1 0 1\n")
    with pytest.raises(ValueError, match="announces 4 images"):
        read_lp(p)


def test_lp_line_without_direction_is_refused(tmp_path):
    p = tmp_path / "bad.lp"
    p.write_text("2\na.jpg 0 0 1\nb.jpg 0 one 1\n")
    with pytest.raises(ValueError, match="line 3"):
        read_lp(p)


def test_image_missing_from_lp_is_named(tmp_path):
    lights = LightSet(np.eye(3), ["a.png", "b.png", "c.png"])
    with pytest.raises(ValueError, match="d.png"):
        lights.order_for(["a.png", "d.png", "c.png"])


def test_plain_directions_with_and_without_count(tmp_path):
    a = tmp_path / "a.txt"
    a.write_text("3\n0 0 1\n0 0.6 0.8\n# comment\n0.6 0 0.8\n")
    b = tmp_path / "b.txt"
    b.write_text("0 0 1\n0 0.6 0.8\n0.6 0 0.8\n")
    for p in (a, b):
        lights = read_lights(p)
        assert lights.filenames is None
        np.testing.assert_allclose(lights.directions, [[0, 0, 1], [0, 0.6, 0.8], [0.6, 0, 0.8]])
    with pytest.raises(ValueError, match="3 images but the light file has 2"):
        LightSet(np.eye(3)[:2] + [0, 0, 1]).order_for(["x", "y", "z"])


def test_plain_count_mismatch_is_refused(tmp_path):
    p = tmp_path / "a.txt"
    p.write_text("4\n0 0 1\n0 0.6 0.8\n0.6 0 0.8\n")
    with pytest.raises(ValueError, match="announces 4"):
        read_directions(p)


def test_zero_direction_is_refused():
    with pytest.raises(ValueError, match="zero length"):
        LightSet(np.array([[0, 0, 1], [0, 0, 0], [1, 0, 1]]))


def test_lp_written_then_read_is_the_same(tmp_path):
    rng = np.random.default_rng(1)
    d = rng.normal(size=(5, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.2
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    names = [f"shot_{i:02d}.tif" for i in range(5)]
    write_lp(tmp_path / "x.lp", names, d)
    back = read_lights(tmp_path / "x.lp")
    assert back.filenames == names
    np.testing.assert_allclose(back.directions, d, atol=2e-6)


def test_intensity_file_single_or_rgb(tmp_path):
    p = tmp_path / "e.txt"
    p.write_text("1.0 2.0 3.0\n0.5 0.5 0.5\n")
    np.testing.assert_allclose(read_intensities(p), [[1, 2, 3], [0.5, 0.5, 0.5]])
    q = tmp_path / "f.txt"
    q.write_text("2\n4\n")
    np.testing.assert_allclose(read_intensities(q), [[2, 2, 2], [4, 4, 4]])
    q.write_text("2\n-1\n")
    with pytest.raises(ValueError, match="positive"):
        read_intensities(q)


def test_benchmark_light_files_read(shared_data):
    seitz = read_lights(shared_data / "psm-seitz" / "lights.txt")
    assert len(seitz) == 12 and np.all(seitz.directions[:, 2] > 0)
    ball = read_lights(shared_data / "diligent-ball" / "light_directions.txt",
                       shared_data / "diligent-ball" / "light_intensities.txt")
    assert ball.directions.shape == (96, 3) and ball.intensities.shape == (96, 3)
    np.testing.assert_allclose(np.linalg.norm(ball.directions, axis=1), 1.0)


def test_shell_sorted_lists_are_told_from_natural_ones():
    from common.acquisition.lightfile import natural_order, shell_sorted

    glob = ["d/img1.jpg", "d/img10.jpg", "d/img11.jpg", "d/img2.jpg", "d/img3.jpg"]
    assert shell_sorted(glob)
    assert [glob[i] for i in natural_order(glob)] == ["d/img1.jpg", "d/img2.jpg", "d/img3.jpg", "d/img10.jpg",
                                                      "d/img11.jpg"]
    assert not shell_sorted(["img01.jpg", "img02.jpg", "img10.jpg"])  # zero-padded: both orders agree
    assert not shell_sorted(["img1.jpg", "img2.jpg", "img10.jpg"])    # already natural
    assert not shell_sorted(["img3.jpg", "img1.jpg", "img2.jpg"])     # some other order, chosen on purpose


def test_light_positions_are_kept_in_pixels(tmp_path):
    p = tmp_path / "pos.txt"
    p.write_text("0 0 100\n30 0 40\n0 -60 80\n")
    lights = read_lights(p, positions=2.0)  # 2 px per unit
    np.testing.assert_allclose(lights.positions, [[0, 0, 200], [60, 0, 80], [0, -120, 160]])
    np.testing.assert_allclose(lights.directions[1], [0.6, 0, 0.8])
    assert read_lights(p).positions is None
    with pytest.raises(ValueError, match="not in front"):
        LightSet(np.eye(3), positions=[[0, 0, 1], [0, 0, -1], [1, 0, 1]])
