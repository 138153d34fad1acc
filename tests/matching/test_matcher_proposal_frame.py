"""services/matcher.py: a stored proposal states every pose in one frame (fragment_b in fragment_a's).

docs/messages.md: ``match.proposed`` carries ``pose`` (``other`` in ``fragment``'s frame) and an
``alignment`` whose ``angle_deg``/``tx_mm``/``ty_mm`` are that same pose. When the query fragment
sorts after the other, the matcher inverted ``pose`` but kept the alignment's pose in the query's
frame, so the two disagreed in the message and on the review page.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from common.matching.alignment import Alignment, pose_matrix
from common.matching.index import Candidate


def _state():
    cues = {f: SimpleNamespace(patch_index=np.arange(10)) for f in ("A1", "B2")}
    return SimpleNamespace(index=SimpleNamespace(cues=cues), model=SimpleNamespace(version="m1"))


@pytest.mark.parametrize("query, other", [("B2", "A1"), ("A1", "B2")])
def test_pose_and_alignment_of_a_proposal_are_the_same_pose_of_b_in_a(query, other):
    import services.matcher as matcher
    angle, tx, ty = 30.0, 12.0, -4.0                       # other in the query's frame
    al = Alignment(angle, tx, ty, float("nan"), 25.0, 0.5, 24.0)
    c = Candidate(query, other, 0.8, 2, 3, np.array([[2, 3]]), np.zeros((1, 4)), alignment=al)
    p = matcher._proposal(c, _state(), ["c0", "c1", "c2", "c3"])
    assert (p.fragment_a, p.fragment_b) == ("A1", "B2")
    stored = pose_matrix(p.angle_deg, p.tx_mm, p.ty_mm)    # B2 in A1's frame
    query_frame = pose_matrix(angle, tx, ty)               # other in query's frame
    expected = query_frame if query == "A1" else np.linalg.inv(query_frame)
    np.testing.assert_allclose(stored, expected, atol=1e-9)
    a = p.alignment
    assert (a["angle_deg"], a["tx_mm"], a["ty_mm"]) == pytest.approx((p.angle_deg, p.tx_mm, p.ty_mm))
    assert a["contact_mm"] == 25.0 and a["score"] == 24.0 and math.isnan(a["gap_mm"])
    fields = p.to_event_fields()
    assert fields["pose"]["angle_deg"] == pytest.approx(fields["alignment"]["angle_deg"])
    # patches follow the stored order too
    assert fields["patches"] == ([2, 3] if query == "A1" else [3, 2])


@pytest.mark.parametrize("query, other", [("B2", "A1"), ("A1", "B2")])
def test_a_proposals_alternative_poses_are_in_its_frame_too(query, other):
    """The docking's other candidate poses travel with the proposal (``alignment.alternatives``),
    each stated as fragment_b in fragment_a's frame like the pose, and the message carries them."""
    import services.matcher as matcher
    from common.messages import new_message

    alts = ((120.0, -8.0, 30.0), (-45.0, 5.0, 2.5))         # other in the query's frame
    al = Alignment(30.0, 12.0, -4.0, float("nan"), 25.0, 0.5, 24.0, alts)
    c = Candidate(query, other, 0.8, 2, 3, np.array([[2, 3]]), np.zeros((1, 4)), alignment=al)
    p = matcher._proposal(c, _state(), ["c0", "c1", "c2", "c3"])
    got = p.alignment["alternatives"]
    assert len(got) == 2
    for g, (angle, tx, ty) in zip(got, alts):
        expected = pose_matrix(angle, tx, ty) if query == "A1" else np.linalg.inv(pose_matrix(angle, tx, ty))
        np.testing.assert_allclose(pose_matrix(g["angle_deg"], g["tx_mm"], g["ty_mm"]), expected, atol=1e-9)
    msg = new_message("match.proposed", **p.to_event_fields())
    assert msg["alignment"]["alternatives"] == got
