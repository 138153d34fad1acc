"""A small synthetic wall with features, built once per test session (a few seconds)."""

import pytest


@pytest.fixture(scope="session")
def small_wall():
    from common.matching.online import wall_cues
    from common.synth.wall import generate_wall

    wall = generate_wall(40, seed=3, dpi=60)
    tables, cues, poses = wall_cues(wall)
    return wall, tables, cues, poses
