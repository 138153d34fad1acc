import cv2
import numpy as np
import pytest

from common.synth.dafne import import_dafne


@pytest.fixture(scope="module")
def dafne_dir():
    from tests.conftest import SHARED_DATA
    path = SHARED_DATA / "dafne-adam"
    if not path.is_dir():
        pytest.skip(f"optional DAFNE data set not present at {path}")
    return path


@pytest.fixture(scope="module")
def dafne(dafne_dir):
    return import_dafne(dafne_dir)


def test_dafne_counts_match_the_published_set(dafne):
    placed = [f for f in dafne.fragments if f.pose is not None]
    assert len(placed) == 299
    assert sum(f.spurious for f in dafne.fragments) == 29
    # the README: neighbours are placed masks within 6 px, about 512 pairs
    assert 490 <= len(dafne.adjacency) <= 535
    assert all(f.rgbn.normals is None for f in dafne.fragments)


def _colour_error(frag, fresco, pose):
    pm = frag.rgbn.pixel_mm
    rr, cc = np.nonzero(frag.rgbn.mask)
    a = np.deg2rad(pose[0])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    q = np.round((np.column_stack([cc, rr]) * pm @ R.T + pose[1:]) / pm).astype(int)
    ok = (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < fresco.shape[1]) & (q[:, 1] < fresco.shape[0])
    lin = frag.rgbn.albedo[rr[ok], cc[ok]]
    srgb = np.where(lin <= 0.0031308, lin * 12.92, 1.055 * lin ** (1 / 2.4) - 0.055) * 255
    return np.abs(srgb - fresco[q[ok, 1], q[ok, 0]]).mean()


def test_poses_put_each_fragment_on_its_place_in_the_fresco(dafne, dafne_dir):
    fresco = cv2.imread(str(dafne_dir / "fresco.jpg"))[..., ::-1].astype(float)
    placed = [f for f in dafne.fragments if f.pose is not None][::10]
    right = [_colour_error(f, fresco, f.pose) for f in placed]
    # the same fragments, same centres, rotated the other way round land on the wrong colours
    wrong = []
    for f in placed:
        centre = np.array(f.rgbn.shape[::-1]) / 2.0 * f.rgbn.pixel_mm
        a = np.deg2rad(-f.pose[0])
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        t = f.to_wall(centre[None])[0] - R @ centre
        wrong.append(_colour_error(f, fresco, (-f.pose[0], t[0], t[1])))
    assert np.median(right) < 15
    assert np.median(wrong) > 1.5 * np.median(right)


def test_dafne_correspondences_are_close_on_the_fresco(dafne):
    for a, b, _ in dafne.adjacency[::20]:
        pa, pb = dafne.correspondences[(a, b)]
        if len(pa):
            d = np.hypot(*(dafne.fragment(a).to_wall(pa) - dafne.fragment(b).to_wall(pb)).T)
            assert np.median(d) <= 8 * 25.4 / dafne.dpi


def test_dafne_ground_truth_round_trips(dafne, tmp_path):
    from common.store import Store
    from common.synth import load_groundtruth, save_groundtruth
    store = Store(tmp_path)
    back = load_groundtruth(store, save_groundtruth(store, dafne))
    assert back.adjacency == dafne.adjacency
    assert sum(f.spurious for f in back.fragments) == 29


def test_not_a_dafne_directory_is_refused(tmp_path):
    with pytest.raises(ValueError, match="not a DAFNE set"):
        import_dafne(tmp_path)
