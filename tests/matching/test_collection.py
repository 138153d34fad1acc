"""Real placed collections as ground truth (common/matching/collection.py), checked against a
synthetic wall written in the RePAIR layout, whose poses and neighbours are known independently."""

from math import comb
from pathlib import Path

import numpy as np
import pytest

from common.matching.collection import (collection_wall, piece_pose, relative_pose_error,
                                        within_object_recall)

REPAIR = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "repair-dev"


@pytest.fixture(scope="module")
def synthetic_collection(tmp_path_factory):
    from common.synth.realistic import write_collection
    from common.synth.wall import generate_wall

    wall = generate_wall(16, seed=4, dpi=40, preset="pompeii", colour_only=True)
    root = tmp_path_factory.mktemp("collection")
    write_collection(wall, root)
    return wall, root


def test_collection_poses_place_outlines_where_the_generator_put_them(synthetic_collection):
    import cv2
    from scipy.spatial import cKDTree

    wall, root = synthetic_collection
    got = collection_wall(root, dpi=wall.dpi)
    truth = {f.id: f for f in wall.fragments}
    placed = [f for f in got.fragments if f.pose is not None]
    assert len(placed) == sum(f.pose is not None for f in wall.fragments)
    assert {f.id for f in got.fragments if f.spurious} == {f.id for f in wall.fragments if f.pose is None}

    def to_wall(points, pose):
        r = np.radians(pose[0])
        return points @ np.array([[np.cos(r), -np.sin(r)], [np.sin(r), np.cos(r)]]).T + pose[1:]

    outlines = {}
    for f in placed:   # the outline read back from the picture, placed by the collection's pose
        cs, _ = cv2.findContours(f.rgbn.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        outlines[f.id] = to_wall(max(cs, key=len).reshape(-1, 2) * f.rgbn.pixel_mm, f.pose)
    gen = {f.id: to_wall(truth[f.id].contour_mm, truth[f.id].pose) for f in placed}
    # the two wall frames may differ by the canvas origin only: one offset for all fragments
    offset = np.mean([gen[k].mean(axis=0) - outlines[k].mean(axis=0) for k in outlines], axis=0)
    for k in outlines:
        d, _ = cKDTree(gen[k]).query(outlines[k] + offset)
        assert np.median(d) < 1.0, k   # within a pixel or two (0.64 mm pixels, a soft alpha edge)


def test_collection_neighbours_are_the_walls_long_joins(synthetic_collection):
    wall, root = synthetic_collection
    got = collection_wall(root, dpi=wall.dpi)
    found = {frozenset(p[:2]) for p in got.adjacency}
    long_joins = [frozenset(p[:2]) for p in wall.adjacency if p[2] >= 30.0]
    assert long_joins and np.mean([j in found for j in long_joins]) >= 0.8
    true = {frozenset(p[:2]) for p in wall.adjacency}
    assert np.mean([j in true for j in found]) >= 0.8   # RePAIR's 48-px rule also catches corner neighbours


def test_piece_pose_reads_opencv_rotation_counter_clockwise():
    import cv2
    m = cv2.getRotationMatrix2D((50.0, 50.0), 30.0, 1.0)
    angle, tx, ty = piece_pose(m, 0.5)
    assert angle == pytest.approx(-30.0)
    # the centre stays put: R c + t = c
    a = np.radians(angle)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    assert np.allclose(r @ [25.0, 25.0] + [tx, ty], [25.0, 25.0])


def test_within_object_recall_and_its_random_baseline():
    rankings = {"a": ["b", "c", "d"], "b": ["a", "c", "d"], "c": ["d", "a", "b"], "d": ["a", "b", "c"]}
    neighbours = {"a": {"b"}, "b": {"a", "c"}, "c": {"b"}}
    r = within_object_recall(rankings, neighbours, ks=(1, 2))
    assert r["n"] == 3
    assert r["recall"][1] == pytest.approx(2 / 3)       # a and b hit at 1, c does not
    assert r["recall"][2] == pytest.approx(2 / 3)       # c's b is third
    assert r["incidence"][1] == pytest.approx(2 / 4)    # 4 links, 2 found first
    # random: 1 - C(n-m, k)/C(n, k), averaged; at k=1 it is the mean of m/n (README's definition)
    assert r["random"][1] == pytest.approx(np.mean([1 / 3, 2 / 3, 1 / 3]))
    assert r["random"][2] == pytest.approx(np.mean([1 - comb(2, 2) / comb(3, 2), 1.0, 1 - comb(2, 2) / comb(3, 2)]))


def test_relative_pose_error_is_zero_for_the_truth_and_measures_a_turn():
    pa, pb = (20.0, 5.0, -3.0), (-40.0, 30.0, 12.0)

    def m(p):
        r = np.radians(p[0])
        return np.array([[np.cos(r), -np.sin(r), p[1]], [np.sin(r), np.cos(r), p[2]], [0, 0, 1.0]])
    rel = np.linalg.inv(m(pa)) @ m(pb)
    truth = (float(np.degrees(np.arctan2(rel[1, 0], rel[0, 0]))), rel[0, 2], rel[1, 2])
    assert relative_pose_error(pa, pb, truth, (10.0, 10.0)) == pytest.approx((0.0, 0.0), abs=1e-9)
    turned = (truth[0] + 5.0, truth[1], truth[2])
    ang, shift = relative_pose_error(pa, pb, turned, (0.0, 0.0))
    assert ang == pytest.approx(5.0)
    # a turn about B's origin moves a point r mm from it by 2 r sin(θ/2)
    _, shift = relative_pose_error(pa, pb, turned, (10.0, 0.0))
    assert shift == pytest.approx(2 * 10.0 * np.sin(np.radians(2.5)), rel=1e-6)


def test_collection_refuses_a_missing_directory_and_bad_dpi(tmp_path):
    with pytest.raises(ValueError):
        collection_wall(tmp_path / "absent")
    with pytest.raises(ValueError, match="dpi"):
        collection_wall(tmp_path, dpi=0)


@pytest.mark.data
@pytest.mark.skipif(not REPAIR.is_dir(), reason="../shared/data/repair-dev is absent")
def test_repair_collection_has_its_documented_neighbours():
    wall = collection_wall(REPAIR, dpi=150)
    assert len(wall.fragments) == 30
    assert sum(f.spurious for f in wall.fragments) == 4
    assert 18 <= len(wall.adjacency) <= 24   # "about 22" with the 48 px / 100 px rule
