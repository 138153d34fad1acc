"""Pieces of the evaluation report: the ribbon's run on a contour, the example picture."""

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
