"""Door checks of ``tessera ps`` (issue 16): every refusal exits != 0, names the file and the
reason, and leaves nothing written; position-matched lists in shell order are put right."""

import cv2
import numpy as np

from common.acquisition.handheld import simulate_flash_capture, surface_normals
from common.acquisition.lightfile import write_lp
from common.acquisition.surface import FragmentSurface
from common.rgbn.image import read_rgbn
from services.cli import main as tessera


def _lights(n, seed=3):
    rng = np.random.default_rng(seed)
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(30, 80, n))
    return np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def _surface(size=48):
    rows, cols = np.mgrid[0:size, 0:size].astype(float)
    mask = (np.abs(cols - size / 2) < size * 0.35) & (np.abs(rows - size / 2) < size * 0.3)
    height = (0.3 * cols + 0.1 * np.sin(rows / 4)) * 0.1 + 1.0
    albedo = np.dstack([np.full((size, size), v) for v in (0.8, 0.6, 0.4)]).astype(np.float32)
    return FragmentSurface(albedo, np.where(mask, height, 0.0), mask, 254.0)


def _capture(tmp_path, n=12, names=None, ext="png"):
    surf = _surface()
    lights = _lights(n)
    images = simulate_flash_capture(surf, lights)
    names = names or [f"shot_{i:02d}.{ext}" for i in range(n)]
    for name, img in zip(names, images):
        if ext == "png":
            cv2.imwrite(str(tmp_path / name), np.round(img * 65535).astype(np.uint16)[..., ::-1])
        else:
            cv2.imwrite(str(tmp_path / name), np.round(img * 255).astype(np.uint8)[..., ::-1])
    write_lp(tmp_path / "capture.lp", names, lights)
    np.savetxt(tmp_path / "dirs.txt", lights)
    cv2.imwrite(str(tmp_path / "mask.png"), surf.mask.astype(np.uint8) * 255)
    return surf, [str(tmp_path / nm) for nm in names]


def _nothing_written(tmp_path):
    assert not (tmp_path / "out.h5").exists()
    assert not (tmp_path / "store").exists() or not any(p.is_file() for p in (tmp_path / "store").rglob("*"))
    assert not (tmp_path / "pics").exists() or not any((tmp_path / "pics").iterdir())


def _ps(tmp_path, shots, *extra):
    return tessera(["ps", *shots, *extra, "-o", str(tmp_path / "out.h5"), "--store", str(tmp_path / "store"),
                    "--fragment", "F1", "--pictures", str(tmp_path / "pics"), "--no-discontinuities"])


def test_truncated_jpeg_is_refused_and_nothing_written(tmp_path, capsys):
    _, shots = _capture(tmp_path, ext="jpg")
    data = open(shots[5], "rb").read()
    open(shots[5], "wb").write(data[:len(data) // 2])
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--srgb") == 2
    err = capsys.readouterr().err
    assert "shot_05.jpg" in err and "truncated" in err
    _nothing_written(tmp_path)


def test_all_black_images_with_a_mask_write_no_artifact(tmp_path, capsys):
    _, shots = _capture(tmp_path)
    for s in shots:
        cv2.imwrite(s, np.zeros((48, 48, 3), np.uint16))
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png")) == 2
    captured = capsys.readouterr()
    assert "shot_00.png" in captured.err and "black" in captured.err
    assert "rgbn.ready" not in captured.out  # nothing announced
    _nothing_written(tmp_path)


def test_a_mask_where_no_pixel_can_be_solved_writes_nothing(tmp_path, capsys):
    _, shots = _capture(tmp_path)
    dark = np.zeros((48, 48), np.uint8)
    dark[:3, :3] = 255  # a corner of the table that is black in every image? no: the table is lit...
    for s in shots:  # ... so black out that corner in every image: no light reaches it
        img = cv2.imread(s, cv2.IMREAD_UNCHANGED)
        img[:3, :3] = 0
        cv2.imwrite(s, img)
    cv2.imwrite(str(tmp_path / "corner.png"), dark)
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "corner.png")) == 2
    captured = capsys.readouterr()
    assert "no pixel" in captured.err and "corner.png" in captured.err and "nothing written" in captured.err
    assert "rgbn.ready" not in captured.out
    _nothing_written(tmp_path)


def test_pictures_pointing_at_a_file_is_refused_up_front(tmp_path, capsys):
    _, shots = _capture(tmp_path)
    (tmp_path / "pics").write_text("not a directory")
    code = tessera(["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "-o", str(tmp_path / "out.h5"),
                    "--pictures", str(tmp_path / "pics")])
    assert code == 2
    assert "--pictures" in capsys.readouterr().err
    assert not (tmp_path / "out.h5").exists() and (tmp_path / "pics").read_text() == "not a directory"


def test_too_small_automatic_mask_asks_for_a_mask_file(tmp_path, capsys):
    _, shots = _capture(tmp_path)
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--min-mask-share", "0.9") == 2
    assert "--mask" in capsys.readouterr().err
    _nothing_written(tmp_path)


def test_shell_sorted_images_matched_by_position_are_put_in_natural_order(tmp_path, capsys):
    names = [f"img{i}.png" for i in range(12)]  # img0 .. img11, unpadded
    surf, shots = _capture(tmp_path, names=names)
    glob_order = sorted(shots)  # what `img*.png` gives: img0, img1, img10, img11, img2, ...
    assert glob_order != shots
    code = tessera(["ps", *glob_order, "--lights", str(tmp_path / "dirs.txt"), "--mask", str(tmp_path / "mask.png"),
                    "-o", str(tmp_path / "out.h5"), "--no-discontinuities"])
    assert code == 0
    err = capsys.readouterr().err
    assert "warning" in err and "natural order" in err
    import h5py
    with h5py.File(tmp_path / "out.h5", "r") as f:
        rgbn = read_rgbn(f)
    inner = cv2.erode(surf.mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    err_deg = np.degrees(np.arccos(np.clip((rgbn.normals * surface_normals(surf)).sum(-1), -1, 1)))
    assert err_deg[inner].mean() < 1.0  # paired with the right lights


def test_shell_order_does_not_matter_when_the_light_file_names_the_images(tmp_path, capsys):
    names = [f"img{i}.png" for i in range(12)]
    _, shots = _capture(tmp_path, names=names)
    assert tessera(["ps", *sorted(shots), "--lights", str(tmp_path / "capture.lp"), "--mask",
                    str(tmp_path / "mask.png"), "-o", str(tmp_path / "out.h5"), "--no-discontinuities"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_refused_capture_is_not_submitted(tmp_path, capsys):
    from tests.conftest import free_port

    _, shots = _capture(tmp_path)
    for s in shots:
        cv2.imwrite(s, np.zeros((48, 48, 3), np.uint16))
    cfg = tmp_path / "station.toml"
    cfg.write_text(f'[storage]\nroot = "{tmp_path / "storage"}"\n[broker]\nhost = "127.0.0.1"\nbind = "127.0.0.1"\n'
                   f'port = {free_port()}\nfeed_port = {free_port()}\njournal_dir = "{tmp_path / "journal"}"\n'
                   '[client]\ntimeout_s = 0.5\nretries = 1\n')
    code = tessera(["ps", *shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
                    "--fragment", "F1", "--submit", "--config", str(cfg)])
    captured = capsys.readouterr()
    assert code == 2 and "black" in captured.err  # refused at the door, not "stored but not submitted" (1)
    assert "rgbn.ready" not in captured.out and "not submitted" not in captured.err
    assert not (tmp_path / "storage").exists() or not any(p.is_file() for p in (tmp_path / "storage").rglob("*"))


def test_light_positions_in_millimetres_solve_a_near_lit_plane_flat(tmp_path, capsys):
    from common.acquisition.photometric import point_light_field

    h, w, dpi = 60, 80, 254.0  # 10 px per mm
    rng = np.random.default_rng(2)
    n = 20
    # lamps at scattered heights and distances (no dome), 5-12 mm from the centre of a 6x8 mm plane
    az = rng.uniform(0, 2 * np.pi, n)
    el = np.radians(rng.uniform(30, 80, n))
    dist = rng.uniform(5, 12, n)
    pos_mm = dist[:, None] * np.column_stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    d, f = point_light_field(pos_mm * dpi / 25.4, (h, w))
    grey = (0.6 * np.clip(d[..., 2], 0, None) * f).T.reshape(n, h, w)
    shots = []
    for i, g in enumerate(grey):
        shots.append(str(tmp_path / f"p{i:02d}.png"))
        cv2.imwrite(shots[-1], np.round(np.clip(np.dstack([g] * 3), 0, 1) * 65535).astype(np.uint16))
    np.savetxt(tmp_path / "positions.txt", pos_mm)
    assert tessera(["ps", *shots, "--lights", str(tmp_path / "positions.txt"), "--light-positions",
                    str(dpi / 25.4), "--min-mask-share", "0", "-o", str(tmp_path / "out.h5"),
                    "--no-discontinuities", "--method", "least_squares"]) == 0
    import h5py
    with h5py.File(tmp_path / "out.h5", "r") as fh:
        rgbn = read_rgbn(fh)
    tilt = np.degrees(np.arccos(np.clip(rgbn.normals[..., 2], -1, 1)))[rgbn.mask]
    assert rgbn.mask.mean() > 0.99 and tilt.max() < 0.1


def test_three_images_solve_by_least_squares(tmp_path, capsys):
    # ps asks for at least 3 images; with exactly 3 the least-squares fit is exact (confidence 1), not "unusable"
    surf, shots = _capture(tmp_path, n=3)
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png"),
               "--method", "least_squares") == 0, capsys.readouterr().err
    import h5py
    with h5py.File(tmp_path / "out.h5", "r") as fh:
        rgbn = read_rgbn(fh)
    assert rgbn.mask.any() and rgbn.confidence[rgbn.mask].min() > 0.99


def test_robust_method_with_three_images_is_refused_up_front_with_its_reason(tmp_path, capsys):
    _, shots = _capture(tmp_path, n=3)
    assert _ps(tmp_path, shots, "--lights", str(tmp_path / "capture.lp"), "--mask", str(tmp_path / "mask.png")) == 2
    err = capsys.readouterr().err
    assert "robust" in err and "least_squares" in err and "at least 4" in err
    assert "dark or unusable" not in err
    _nothing_written(tmp_path)
