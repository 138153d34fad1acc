"""Correspondence rows follow the registry's rules; ground-truth pairs face each other on the wall."""

import numpy as np
import pytest

from common.features.registry import correspondence, fragment_descriptors, patch_descriptors
from common.matching.pairs import (check_correspondence_rules, correspondence_columns, pair_group, pair_rows,
                                   strip_gap, training_set, true_patch_pairs)


def test_vectorised_correspondence_agrees_with_the_registry():
    check_correspondence_rules()


def test_pair_rows_hold_registry_correspondences_of_each_patch_pair(small_wall):
    _, _, cues, _ = small_wall
    a, b = [c for c in cues.values() if len(c) > 3][:2]
    rows = pair_rows(a, b, [0, 2], [1, 3])
    cols = correspondence_columns()
    fd, pd = fragment_descriptors(), patch_descriptors()
    for k, d in enumerate(fd):
        assert rows[0, cols.index(d.key)] == pytest.approx(correspondence(d, a.values[k], b.values[k]), nan_ok=True)
    for k, d in enumerate(pd):
        want = correspondence(d, a.patches[2, k], b.patches[3, k])
        assert rows[1, cols.index(d.key)] == pytest.approx(want, nan_ok=True)


def test_strip_gap_is_zero_for_a_strip_against_itself_reversed_and_moved():
    rng = np.random.default_rng(1)
    s = np.cumsum(rng.normal(size=(3, 15, 2)), axis=1)
    s -= s.mean(axis=1, keepdims=True)
    th = 0.7
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    partner = (s @ rot.T)[:, ::-1, :]   # the neighbour traverses the shared break backwards
    assert np.allclose(strip_gap(s, partner), 0.0, atol=1e-6)
    assert np.all(strip_gap(s, partner[[1, 2, 0]]) > 0.3)


def test_true_patch_pairs_lie_close_and_face_each_other_on_the_wall(small_wall):
    wall, _, cues, poses = small_wall
    checked = 0
    for a, b, shared in wall.adjacency:
        pairs = true_patch_pairs(cues[a], poses[a], cues[b], poses[b])
        if len(pairs) == 0:
            continue
        fa, fb = wall.fragment(a), wall.fragment(b)
        pa = fa.to_wall(cues[a].points_mm[pairs[:, 0]])
        pb = fb.to_wall(cues[b].points_mm[pairs[:, 1]])
        assert np.all(np.linalg.norm(pa - pb, axis=1) <= 2.5 + 1e-9)
        checked += 1
    assert checked >= len(wall.adjacency) // 3
    # fragments that are not neighbours never have matching patch pairs
    neigh = {tuple(sorted(p[:2])) for p in wall.adjacency}
    ids = [f.id for f in wall.fragments if not f.spurious]
    far = next((a, b) for a in ids for b in ids if a < b and (a, b) not in neigh
               and np.linalg.norm(np.array(poses[a][1:]) - np.array(poses[b][1:])) > 200)
    assert len(true_patch_pairs(cues[far[0]], poses[far[0]], cues[far[1]], poses[far[1]])) == 0


def test_training_set_keeps_the_stated_imbalance_and_groups_by_pair(small_wall):
    wall, _, cues, poses = small_wall
    ts = training_set(cues, poses, wall.adjacency, negatives_per_positive=4, seed=2)
    n_pos = int(ts.y.sum())
    assert n_pos > 20
    assert (len(ts) - n_pos) == pytest.approx(4 * n_pos, abs=8)
    assert ts.negatives_per_positive == pytest.approx(4.0, abs=0.1)
    neigh = {tuple(sorted(p[:2])) for p in wall.adjacency}
    for (a, b), y, g in zip(ts.fragments, ts.y, ts.groups):
        assert ((a, b) in neigh) == bool(y)
        assert g == pair_group(b, a)
    assert ts.x.shape == (len(ts), len(correspondence_columns()))


def test_training_set_refuses_a_bad_ratio(small_wall):
    wall, _, cues, poses = small_wall
    with pytest.raises(ValueError, match="negatives_per_positive"):
        training_set(cues, poses, wall.adjacency, negatives_per_positive=0)
