"""Pieces of the evaluation report: the ribbon's run on a contour, the example picture."""

from pathlib import Path

import numpy as np

from common.matching.report import _plot_ribbon_examples, _run_points


def test_run_points_are_the_contour_within_half_a_run_of_the_centre_arc_wrapping_at_the_start():
    # a 40 × 40 mm square sampled every 1 mm from (0, 0), clockwise on screen: arc = position
    side = np.arange(40.0)
    square = np.vstack([np.column_stack([side, 0 * side]), np.column_stack([40 + 0 * side, side]),
                        np.column_stack([40 - side, 40 + 0 * side]), np.column_stack([0 * side, 40 - side])])
    run = _run_points(square, 45.0, 10.0)           # arcs 35…55: the top edge's end, the right edge
    assert len(run) == 21 and run[0].tolist() == [35.0, 0.0] and run[-1].tolist() == [40.0, 15.0]
    wrapped = _run_points(square, 2.0, 5.0)         # arcs 157…160 and 0…7
    assert len(wrapped) == 11 and wrapped[0].tolist() == [0.0, 3.0] and wrapped[-1].tolist() == [7.0, 0.0]


def test_ribbon_example_picture_shows_true_neighbours_found_first(small_wall, tmp_path):
    import matplotlib.image as mpimg

    from common.matching.online import ribbon_calibration, train_model
    from common.matching.pairs import training_set
    from common.matching.report import _index_of

    wall, tables, cues, poses = small_wall
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1),
                           ribbon=ribbon_calibration(tables, wall.adjacency))
    path = tmp_path / "ribbon.png"
    _plot_ribbon_examples(wall, tables, _index_of(tables, cues), model, path, n=2)
    img = mpimg.imread(path)
    assert img.shape[:2] == (2 * 232, 512)         # two rows (2.9 in at 80 dpi each) of query | neighbour


def test_collection_evaluation_ranks_a_synthetic_collection_and_beats_chance(small_wall, tmp_path):
    """``evaluate_collection`` on a RePAIR-layout collection written from a realistic synthetic wall
    (plaster lost along its cracks): every figure is in range and consistent, the docking stage gives
    every true pair a pose, and the pictures are written. (How well it ranks is measured by
    ``tessera evaluate``, docs/matching.md; this wall is too small to judge it.)"""
    import json
    from dataclasses import replace

    from common.matching.online import train_model
    from common.matching.pairs import training_set
    from common.matching.report import evaluate_collection
    from common.synth.realistic import write_collection
    from common.synth.wall import generate_wall

    wall, tables, cues, poses = small_wall
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1))
    model = replace(model, docking=(0.05, -3.0))
    real = generate_wall(14, seed=8, dpi=30, preset="pompeii", colour_only=True)
    write_collection(real, tmp_path / "collection")
    # RePAIR's neighbour rule (48 px along 100 px at ~187 dpi) scaled to these 30-dpi pictures
    res = evaluate_collection(tmp_path / "collection", dpi=30, model=model, out_dir=tmp_path / "out",
                              near_px=48 * 30 / 187, min_run_px=100 * 30 / 187)
    assert res["n_fragments"] == len(real.fragments) and res["n_true_pairs"] > 5
    for k in (1, 5, 10):
        assert 0.0 <= res["pooled_topk"][k] <= 1.0
    assert res["pooled_topk"][1] <= res["pooled_topk"][5] <= res["pooled_topk"][10]
    assert 0.0 <= res["pose_accuracy"] <= 1.0 and 0.0 <= res["pair_ap"] <= 1.0
    # stepping through the alternatives finds at least what the proposed pose gets right; a pair whose
    # proposed pose is right is found at once
    assert res["pose_accuracy"] <= res["pose_offered"] <= 1.0
    for e in res["pose_errors"]:
        if e["angle_deg"] <= 5 and e["shift_mm"] <= 5:
            assert e["right_pose_offered"] == 0
        # what is offered is chosen among the docking's candidates: offered right means a right candidate
        if e["right_pose_offered"] is not None:
            assert e["right_candidate"] is not None
    assert res["pose_offered"] <= res["pose_reachable"] == \
        sum(e["right_candidate"] is not None for e in res["pose_errors"]) / res["n_true_pairs"]
    assert all(e["angle_deg"] is not None for e in res["pose_errors"])   # every true pair was docked
    # a wrong best pose above the truth is counted, a right one is not
    assert res["wrong_pose_scores_above_truth"] == sum(1 for e in res["pose_errors"] if e["best_right"] is False
                                                       and e["score_best"] > e["score_at_truth"])
    assert all(e["best_right"] is not None for e in res["pose_errors"])
    assert res["within_object_recall"][3] >= res["within_object_recall"][1]
    assert res["within_object_random"][3] >= res["within_object_random"][1] > 0
    # each figure lies within its bootstrap interval (resampling what it was counted on)
    iv = res["intervals"]
    for k in (1, 5, 10):
        assert iv["pooled_topk"][k][0] <= res["pooled_topk"][k] <= iv["pooled_topk"][k][1]
    for k in (1, 3):
        assert iv["within_object_recall"][k][0] <= res["within_object_recall"][k] <= iv["within_object_recall"][k][1]
    assert iv["pose_accuracy"][0] <= res["pose_accuracy"] <= iv["pose_accuracy"][1]
    assert (tmp_path / "out" / "collection_examples.png").stat().st_size > 1000
    json.dumps(res, default=float)


def test_evaluate_collection_command_refuses_a_missing_directory(tmp_path, capsys):
    import pytest

    from services.cli import main

    with pytest.raises(SystemExit, match="no such directory"):
        main(["evaluate", "--collection", str(tmp_path / "absent")])


def test_evaluate_collection_command_draws_beside_the_json_file_or_in_the_current_folder(tmp_path, monkeypatch):
    """The picture of hits and misses goes where the user asked for the figures (the --json file's folder), or
    into the current folder, never into a ``docs/matching`` made under wherever the command runs; ``--out`` wins."""
    import pytest

    import common.matching.report as report
    from services.cli import main

    (tmp_path / "coll").mkdir()
    seen = []

    def record(path, *, out_dir=None, **kw):
        seen.append(Path(out_dir))
        raise ValueError("stopped after the output folder")

    monkeypatch.setattr(report, "evaluate_collection", record)
    monkeypatch.chdir(tmp_path)
    for extra in (["--json", str(tmp_path / "res" / "r.json")], [], ["--json", "r.json", "--out", "pics"]):
        with pytest.raises(SystemExit, match="stopped after the output folder"):
            main(["evaluate", "--collection", str(tmp_path / "coll")] + extra)
    assert seen == [tmp_path / "res", Path("."), Path("pics")]
    assert not (tmp_path / "docs").exists()


def test_a_variant_of_a_collection_is_counted_against_the_pairs_given(tmp_path, small_wall):
    # tests/bench/bench_scan_variants.py counts a collection scanned otherwise against the published one's
    # neighbour pairs (adjacency=): the pairs given are the ones counted, and a pair naming a fragment the
    # collection does not hold is refused before any work
    import pytest

    from common.matching.collection import collection_wall
    from common.matching.online import train_model
    from common.matching.pairs import training_set
    from common.matching.report import evaluate_collection
    from common.synth.realistic import write_collection
    from common.synth.wall import generate_wall

    wall, tables, cues, poses = small_wall
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1))
    write_collection(generate_wall(8, seed=9, dpi=30, preset="pompeii", colour_only=True), tmp_path / "c")
    rule = {"near_px": 48 * 30 / 187, "min_run_px": 100 * 30 / 187}
    pairs = collection_wall(tmp_path / "c", dpi=30, **rule).adjacency
    assert len(pairs) >= 3
    res = evaluate_collection(tmp_path / "c", dpi=30, model=model, adjacency=pairs[:2], **rule)
    assert res["n_true_pairs"] == 2 and len(res["pose_errors"]) == 2
    with pytest.raises(ValueError, match="adjacency names fragments not in .*: nowhere"):
        evaluate_collection(tmp_path / "c", dpi=30, model=model, adjacency=[(pairs[0][0], "nowhere", 10.0)], **rule)
