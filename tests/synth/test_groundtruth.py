import numpy as np
import pytest

from common.store import ArtifactError, Store
from common.synth import generate_wall, load_groundtruth, save_groundtruth


def test_ground_truth_round_trips_through_the_store(tmp_path):
    wall = generate_wall(8, seed=3, dpi=40)
    store = Store(tmp_path)
    ref = save_groundtruth(store, wall)
    assert ref.path == f"groundtruth/{wall.id}.h5"
    back = load_groundtruth(store, ref)
    assert back.id == wall.id and back.adjacency == wall.adjacency
    assert back.n_missing == wall.n_missing and back.params == wall.params
    for f, g in zip(wall.fragments, back.fragments):
        assert (f.id, f.pose, f.spurious, f.notes) == (g.id, g.pose, g.spurious, g.notes)
        assert np.array_equal(f.contour_mm, g.contour_mm)
    for key, (pa, pb) in wall.correspondences.items():
        qa, qb = back.correspondences[key]
        assert np.array_equal(pa, qa) and np.array_equal(pb, qb)
    assert back.preview["labels"].shape == wall.preview["labels"].shape


def test_a_damaged_ground_truth_file_is_refused(tmp_path):
    wall = generate_wall(3, seed=1, dpi=30)
    store = Store(tmp_path)
    ref = save_groundtruth(store, wall)
    with open(store.path(ref.path), "r+b") as fh:
        fh.seek(ref.bytes // 2)
        chunk = fh.read(64)
        fh.seek(ref.bytes // 2)
        fh.write(bytes(b ^ 0xFF for b in chunk))
    with pytest.raises(ArtifactError, match="sha256"):
        load_groundtruth(store, ref)


def test_patch_pairs_match_only_across_a_true_join():
    from common.synth.groundtruth import label_patch_pairs
    wall = generate_wall(10, seed=6, dpi=40)
    (a, b, _), = wall.adjacency[:1]
    pa, pb = wall.correspondences[(a, b)]
    lab = label_patch_pairs(wall, a, pa, b, pb, tol_mm=3.0)
    assert np.all(np.diag(lab))                         # each point faces its partner
    far = np.hypot(*(pb[:, None] - pb[None]).transpose(2, 0, 1)) > 10
    assert not np.any(lab & far)                        # not points far along the crack
    assert np.array_equal(label_patch_pairs(wall, b, pb, a, pa, tol_mm=3.0), lab.T)  # symmetric
    neighbours = set(wall.neighbours(a)) | {a}
    other = next(f.id for f in wall.fragments if f.id not in neighbours)
    assert not label_patch_pairs(wall, a, pa, other, wall.fragment(other).contour_mm[::10]).any()
