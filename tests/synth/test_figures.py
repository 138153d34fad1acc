import numpy as np

from common.synth import figures, generate_wall


def test_pictures_of_a_wall(tmp_path):
    wall = generate_wall(6, seed=3, dpi=40)
    w = figures.wall_picture(wall, width=300)
    c = figures.crack_picture(wall, width=300)
    assert w.shape[1] == c.shape[1] == 300 and w.dtype == np.uint8
    sheet = figures.fragment_sheet(wall.fragments[:3], tile=60, columns=2)
    assert sheet.shape[0] >= 2 * 60
    re = figures.reassembly_picture(wall, [figures.thumbnail(f, 1.0) for f in wall.fragments], mm_per_px=1.0)
    # placed fragments cover a good part of the wall (missing pieces and gaps do not)
    assert 0.3 < np.mean(re.max(axis=2) > 30) < 0.95
    figures.save_png(tmp_path / "x.png", re)
    assert (tmp_path / "x.png").stat().st_size > 0
