"""Docking with kept frames (docking.DockingFrame / dock_frames) and stage 3's one docking per pair:
the same poses as docking from scratch, poses where their scores are, each pair docked once."""

from dataclasses import replace

import numpy as np
import pytest

from common.matching.docking import (Docking, DockingFrame, dock_frames, dock_outlines, docking_score_at,
                                     invert_docking)
from common.matching.index import MatchIndex
from tests.matching.test_docking import _broken_slab, _move
from tests.matching.test_index import _model


def test_kept_frames_dock_as_from_scratch():
    """One fragment's frame serving partners of other sizes (its spectra kept per FFT size, dropped and
    recomputed when the size changes) gives exactly the poses of docking each pair from scratch."""
    a, b = _broken_slab(5, gap_mm=3.0)
    c, d = _broken_slab(6, gap_mm=3.0, size_mm=60.0)
    query = _move(b, 63.0, (80.0, 10.0))
    frame = DockingFrame(query)
    for other in (a, c, d, a):
        kept = dock_frames(DockingFrame(other), frame, n_poses=30, per_angle=3)
        assert kept == dock_outlines(other, query, n_poses=30, per_angle=3)
        assert dock_frames(DockingFrame(other), frame, n_poses=1) == dock_outlines(other, query, n_poses=1)
    assert 0 < frame.nbytes
    frame.clear()
    assert frame.nbytes == 0
    with pytest.raises(ValueError, match="share the grid"):
        dock_frames(DockingFrame(a), DockingFrame(b, cell_mm=2.0))
    with pytest.raises(ValueError, match="sizes_kept"):
        DockingFrame(a, sizes_kept=0)


def test_pose_of_a_small_piece_at_the_far_end_of_a_large_one():
    """A 200 mm slab broken 15 mm from its right end (3 mm lost along a wavy crack): the small end piece,
    turned and moved, docks back where it broke off, and its reported score is the score at the reported
    pose (a shift past half the FFT size is a positive one when the held fragment is that large)."""
    px = 0.25
    y = np.arange(0.0, 60.0 + px, px)
    crack = 185.0 + 4.0 * np.sin(y / 7.0)
    big = np.vstack([[[0.0, 0.0]], np.column_stack([crack - 1.5, y]), [[0.0, 60.0]]])
    small = np.vstack([np.column_stack([crack + 1.5, y])[::-1], [[200.0, 0.0], [200.0, 60.0]]])[::-1]
    moved = _move(small, 120.0, (30.0, 50.0))
    best = dock_outlines(big, moved)[0]
    truth = invert_docking(Docking(120.0, 30.0, 50.0, 0.0, 0.0, 0.0))
    centre = moved.mean(axis=0)
    at_best = _move(centre[None], best.angle_deg, (best.tx_mm, best.ty_mm))[0]
    at_truth = _move(centre[None], truth.angle_deg, (truth.tx_mm, truth.ty_mm))[0]
    assert abs((best.angle_deg - truth.angle_deg + 180) % 360 - 180) <= 4.0
    assert np.hypot(*(at_best - at_truth)) <= 3.0 + 1.5
    assert docking_score_at(big, moved, (best.angle_deg, best.tx_mm, best.ty_mm)) == pytest.approx(best.score, rel=0.1)
    for d in dock_outlines(big, moved, n_poses=10, per_angle=3):   # every candidate, not only the best
        assert docking_score_at(big, moved, (d.angle_deg, d.tx_mm, d.ty_mm)) == pytest.approx(d.score, rel=0.2, abs=3)


def test_stage_three_docks_each_pair_once_for_pose_and_paint(small_wall, monkeypatch):
    """With paint, each docked pair is searched once: its best candidate is the pair's pose (the full
    search's best) and the same candidates give the paint; a tiny frame budget keeps two frames and
    changes nothing."""
    import common.matching.index as index_mod

    wall, tables, cues, poses = small_wall
    model = replace(_model(small_wall), docking=(0.05, -2.0))
    ids = [f for f in cues if len(cues[f]) >= 3 and tables[f].boundary_profile is not None][:8]
    calls = []

    def counted(*args, **kw):
        calls.append(kw.get("n_poses"))
        return dock_frames(*args, **kw)

    monkeypatch.setattr(index_mod, "dock_frames", counted)
    ranked = {}
    for budget in (512, 0):
        monkeypatch.setattr(index_mod, "DOCK_FRAMES_MB", budget)
        index = MatchIndex()
        for f in ids:
            index.add(cues[f], tables[f].contour_mm, tables[f].boundary_profile)
        calls.clear()
        head = index.rank(cues[ids[0]], ids[1:], model, dock_candidates=3)[:3]
        assert calls == [index_mod.DOCK_PAINT_POSES] * 3           # one search per docked pair
        for c in head:
            a, b = sorted((ids[0], c.other))
            full = dock_outlines(tables[a].contour_mm, tables[b].contour_mm, n_poses=1, coarse_angles=0)[0]
            assert index.docking(a, b) == full
            assert np.isfinite(index.paint_pair(c.other, ids[0]))
        assert len(calls) == 3                                      # paint and pose were cached
        ranked[budget] = [(c.other, c.probability, c.paint_mm) for c in head]
        if budget == 0:
            assert len(index._frames) == 2
    assert ranked[0] == ranked[512]


def test_coarse_candidate_search_finds_the_full_searchs_best():
    """``coarse_poses``: the 30-pose search on the coarse grid first, then only its candidates' rotations
    on the fine grid — the best pose within a step and two cells of the full search's, fewer rotations."""
    a, b = _broken_slab(5, gap_mm=3.0)
    moved = _move(b, 63.0, (80.0, 10.0))
    full = dock_outlines(a, moved, n_poses=30, per_angle=3)
    quick = dock_frames(DockingFrame(a), DockingFrame(moved), n_poses=30, per_angle=3, coarse_poses=10)
    # at most 3 poses on each of the (up to) 10 rotations searched finely, plus the best refined a third step
    assert 10 <= len(quick) <= 30 and len({round(d.angle_deg, 3) for d in quick}) <= 10 + 1
    assert abs((full[0].angle_deg - quick[0].angle_deg + 180) % 360 - 180) <= 4.0 + 1e-6
    c = moved.mean(axis=0)
    at_full = _move(c[None], full[0].angle_deg, (full[0].tx_mm, full[0].ty_mm))[0]
    at_quick = _move(c[None], quick[0].angle_deg, (quick[0].tx_mm, quick[0].ty_mm))[0]
    assert np.hypot(*(at_full - at_quick)) <= 3.0
    assert quick[0].score >= 0.95 * full[0].score
