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
        fh.write(b"\0" * 64)
    with pytest.raises(ArtifactError, match="sha256"):
        load_groundtruth(store, ref)
