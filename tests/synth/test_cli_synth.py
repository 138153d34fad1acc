import numpy as np

from common.acquisition.capture import read_scans
from common.rgbn.image import load_rgbn
from common.store import Store
from common.synth import load_groundtruth
from services.cli import main


def _artifacts(root):
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*.h5"))


def test_synth_writes_rgbn_and_ground_truth_reproducibly(tmp_path, capsys):
    for name in ("a", "b"):
        assert main(["synth", "--fragments", "5", "--seed", "9", "--store", str(tmp_path / name), "--dpi", "40"]) == 0
    out = capsys.readouterr()
    assert "fragment" in out.err  # progress per fragment
    files_a, files_b = _artifacts(tmp_path / "a"), _artifacts(tmp_path / "b")
    # content-keyed names: same seed -> the same files
    assert files_a == files_b
    rgbn = [f for f in files_a if "/rgbn/front-" in f]
    gt = [f for f in files_a if f.startswith("groundtruth/")]
    assert len(rgbn) == 5 and len(gt) == 1
    store = Store(tmp_path / "a")
    wall = load_groundtruth(store, gt[0])
    assert sorted(f.id for f in wall.fragments) == sorted(f.split("/")[1] for f in rgbn)
    img = load_rgbn(store, rgbn[0])
    assert img.normals is not None and img.height_mm is not None and img.dpi == 40
    n = img.normals[img.mask]
    assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-4) and np.all(n[:, 2] > 0)


def test_synth_as_scans_goes_through_the_simulated_flatbed(tmp_path):
    # seed 1: a fragment without black paint (the pre-scan cannot tell black paint from the dark lid)
    args = ["synth", "--fragments", "1", "--seed", "1", "--store", str(tmp_path), "--dpi", "40", "--as", "scans",
            "--colour-only", "--missing", "0", "--spurious", "0"]
    assert main(args) == 0
    scans = [f for f in _artifacts(tmp_path) if "/scans/" in f]
    assert len(scans) == 1
    res = read_scans(Store(tmp_path), scans[0])
    assert len(res.scans["front"]) == 1 and len(res.scans["back"]) == 1
    img = res.scans["front"][0].image
    assert img.ndim == 3 and img.shape[2] == 3 and img.max() > img.min()


def test_synth_refuses_a_bad_fragment_count(tmp_path, capsys):
    assert main(["synth", "--fragments", "0", "--store", str(tmp_path)]) == 2
    assert "--fragments" in capsys.readouterr().err


def test_synth_paints_a_user_picture(tmp_path):
    import cv2
    pic = np.zeros((40, 80, 3), np.uint8)
    pic[:, :, 1] = 180  # a green wall (BGR order on disk)
    cv2.imwrite(str(tmp_path / "wall.png"), pic)
    store = tmp_path / "s"
    assert main(["synth", "--fragments", "3", "--seed", "1", "--store", str(store), "--dpi", "30", "--image",
                 str(tmp_path / "wall.png"), "--image-width-mm", "160", "--spurious", "0"]) == 0
    rgbn = [f for f in _artifacts(store) if "/rgbn/" in f]
    assert len(rgbn) == 3
    for path in rgbn:
        img = load_rgbn(Store(store), path)
        mean = img.albedo[img.mask].mean(axis=0)
        # green stays the strongest channel even on a faded or tinted fragment
        assert mean[1] > 1.2 * max(mean[0], mean[2])


def test_synth_refuses_a_missing_picture(tmp_path, capsys):
    assert main(["synth", "--fragments", "2", "--store", str(tmp_path), "--image", str(tmp_path / "none.png")]) == 2
    err = capsys.readouterr().err
    assert "--image" in err and "none.png" in err and "does not exist" in err, err


def test_synth_refuses_a_truncated_picture_naming_it(tmp_path, capsys):
    # OpenCV alone would paint the wall with the missing rows grey
    import cv2
    rng = np.random.default_rng(0)
    cv2.imwrite(str(tmp_path / "wall.png"), rng.integers(0, 255, (60, 80, 3), dtype=np.uint8))
    (tmp_path / "wall.png").write_bytes((tmp_path / "wall.png").read_bytes()[:-500])
    assert main(["synth", "--fragments", "2", "--store", str(tmp_path / "s"), "--image", str(tmp_path / "wall.png")]) == 2
    err = capsys.readouterr().err
    assert "wall.png" in err and "truncated" in err, err


def test_synth_pompeii_writes_a_collection_and_compares_it(tmp_path, capsys):
    coll = tmp_path / "coll"
    args = ["synth", "--preset", "pompeii", "--fragments", "5", "--seed", "4", "--dpi", "30", "--colour-only",
            "--collection", str(coll)]
    assert main(args) == 0
    walls = [p for p in coll.iterdir() if p.is_dir() and (p / "truth.csv").is_file()]
    assert len(walls) == 1 and len(list(walls[0].glob("*.png"))) >= 4
    assert not list(tmp_path.rglob("*.h5"))  # no --store: nothing but the collection
    capsys.readouterr()
    # compare a second wall with the first one's collection, measured by the same code
    assert main(["synth", "--preset", "pompeii", "--fragments", "5", "--seed", "5", "--dpi", "30", "--colour-only",
                 "--compare", str(coll), "--compare-dpi", "30"]) == 0
    out = capsys.readouterr().out
    assert "smallest gap per pair" in out and "plain edge share" in out


def test_synth_compare_with_a_missing_collection_fails_before_generating(tmp_path, capsys):
    assert main(["synth", "--preset", "pompeii", "--fragments", "5", "--compare", str(tmp_path / "nope"),
                 "--store", str(tmp_path / "s")]) == 2
    assert "nope" in capsys.readouterr().err and not (tmp_path / "s").exists()


def test_synth_help_gives_the_pompeii_presets_own_defaults(capsys):
    # the help's "pompeii" defaults are the preset's values (docs/synth.md: median 90 mm, 25 % missing)
    import pytest

    from common.synth.realistic import PRESETS
    with pytest.raises(SystemExit):
        main(["synth", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"pompeii {PRESETS['pompeii']['median_size_mm']:g})" in text
    assert f"pompeii {PRESETS['pompeii']['missing_fraction']:g})" in text
