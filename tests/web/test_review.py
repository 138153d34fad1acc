"""Tests of common/web/review.py: reading the matcher's proposal store, pictures of proposals."""

import threading

import cv2
import numpy as np
import pytest

from common.matching.proposals import Proposal, ProposalStore
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from common.web.review import ReviewData, relief_picture


def _fragment(store, fid, shape=(40, 50)):
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    mask = (yy - h / 2) ** 2 + (xx - w / 2) ** 2 < (min(h, w) / 2.2) ** 2
    n = np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))])
    save_rgbn(store, f"fragments/{fid}/rgbn/front-0.h5", RGBNImage(np.full((h, w, 3), 0.5), mask, 200, normals=n))


@pytest.fixture
def review(tmp_path):
    store = Store(tmp_path)
    for fid in ("A", "B", "C"):
        _fragment(store, fid)
    db_path = tmp_path / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        db.upsert([Proposal("A", "B", 0.8, "m1", angle_deg=10.0, tx_mm=6.0, ty_mm=0.5),
                   Proposal("A", "C", 0.6, "m1")])
    return ReviewData(db_path, store), db_path


def test_reads_see_the_matchers_later_writes_and_verdicts(review):
    data, db_path = review
    assert [p["fragment_b"] for p in data.pending()] == ["B", "C"]
    with ProposalStore(db_path) as db:   # the matcher, in another connection
        db.upsert([Proposal("B", "C", 0.95, "m2")])
        db.record_verdict("A", "B", "rejected", by="x")
        db.record_verdict("A", "C", "confirmed", by="y")
    assert [(p["fragment_a"], p["fragment_b"]) for p in data.pending()] == [("B", "C")]
    assert [v["verdict"] for v in data.history()] == ["confirmed", "rejected"]   # newest first
    assert data.counts() == {"pending": 1, "confirmed": 1, "rejected": 1}


def test_a_proposal_id_that_is_not_a_whole_number_names_no_proposal(review):
    """A verdict's ``"proposal": 1.9`` (a script's arithmetic slip) was taken as proposal 1 and the verdict sent
    for a pair nobody looked at; ids given as whole numbers, in any JSON form, still name their proposal."""
    data, _ = review
    pid = data.pending()[0]["id"]
    assert data.proposal(pid)["id"] == data.proposal(float(pid))["id"] == data.proposal(str(pid))["id"] == pid
    for wrong in (pid + 0.9, pid - 0.5, float("nan"), float("inf"), f"{pid}.9"):
        assert data.proposal(wrong) is None, wrong


def test_many_request_threads_share_one_read_only_connection(review):
    data, _ = review
    errors = []

    def work():
        try:
            for _ in range(20):
                assert len(data.pending()) == 2
        except Exception as exc:  # collected, re-raised below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    with pytest.raises(Exception):   # read-only: the page can never write the matcher's database
        data._db()._db.execute("DELETE FROM proposals")


def test_no_database_yet_means_nothing_to_review(tmp_path):
    data = ReviewData(tmp_path / "absent.sqlite", Store(tmp_path))
    assert data.pending() == [] and data.history() == [] and data.proposal(1) is None
    assert not (tmp_path / "absent.sqlite").exists()


def test_pictures_of_a_proposal(review):
    data, _ = review
    pid = data.pending()[0]["id"]
    for view in ("pair-colour", "pair-relief", "joined-colour", "joined-relief"):
        img = cv2.imdecode(np.frombuffer(data.picture(pid, view, max_side_px=200), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and max(img.shape[:2]) <= 200, view
    no_pose = data.pending()[1]["id"]
    with pytest.raises(LookupError, match="pose"):
        data.picture(no_pose, "joined-colour")
    assert data.picture(no_pose, "pair-colour")[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="view"):
        data.picture(pid, "sideways")
    with pytest.raises(LookupError):
        data.picture(9999, "pair-colour")


def test_a_decided_proposal_stands_at_the_pose_kept_with_its_verdict(review):
    """A confirmed proposal was shown (and confirmed again) at the matcher's proposed pose, not at the corrected
    pose stored with the confirmation: it stands at its latest verdict's pose now, recorded or only sent."""
    data, db_path = review
    pid = data.pending()[0]["id"]
    proposed = {"angle_deg": 10.0, "tx_mm": 6.0, "ty_mm": 0.5}
    corrected = {"angle_deg": 12.0, "tx_mm": 6.8, "ty_mm": -7.5}   # the conservator moved B by ~8 mm
    undecided = data.proposal(pid)
    assert undecided["pose"] == undecided["proposed_pose"] == proposed and undecided["verdict_pose"] is None
    plain = data.picture(pid, "joined-colour", max_side_px=200)
    with ProposalStore(db_path) as db:   # the matcher records the confirmation with its corrected pose
        db.record_verdict("A", "B", "confirmed", pose=corrected, when=100.0)
    got = data.proposal(pid)
    assert got["pose"] == got["verdict_pose"] == pytest.approx(corrected) and got["proposed_pose"] == proposed
    assert got["verdict"] == "confirmed"
    assert data.ranked("B")[0]["pose"] == pytest.approx(corrected)   # the fragment's list (fragment page) too
    # the joined pictures show it; the adjustments (pose controls, "other pose") start from it
    shown = data.picture(pid, "joined-colour", max_side_px=200)
    assert shown == data.picture(pid, "joined-colour", max_side_px=200, pose=corrected) and shown != plain
    assert data.adjusted_pose(pid) == pytest.approx(corrected)
    # a verdict sent and not yet recorded stands in for it; once the matcher records it (same time), the store's
    again = {"angle_deg": 12.0, "tx_mm": 7.3, "ty_mm": -7.5}
    data.sent(pid, "confirmed", again, 200.0)
    assert data.proposal(pid)["pose"] == pytest.approx(again)
    with ProposalStore(db_path) as db:
        db.record_verdict("A", "B", "confirmed", pose=again, when=200.0)
    assert data.proposal(pid)["pose"] == pytest.approx(again) and not data._sent
    # a verdict given elsewhere later than one sent here wins
    data.sent(pid, "confirmed", corrected, 300.0)
    with ProposalStore(db_path) as db:
        db.record_verdict("A", "B", "rejected", when=400.0)   # no pose given: the proposal's is kept with it
    assert data.proposal(pid)["pose"] == proposed and data.proposal(pid)["verdict"] == "rejected"


def test_the_pair_picture_draws_both_fragments_at_one_scale(tmp_path):
    """The side-by-side picture scaled both fragments to one height: a 105 mm piece was drawn as tall as a
    149 mm one. It is at one mm a pixel now, whatever the dpi of each (here 100 and 50 dpi)."""
    store = Store(tmp_path)
    for fid, height_mm, dpi in (("P1", 105.0, 100.0), ("P2", 149.0, 50.0)):
        h, w = int(round(height_mm / 25.4 * dpi)), int(round(40 / 25.4 * dpi))
        mask = np.zeros((h, w), bool)
        mask[2:-2, 2:-2] = True
        save_rgbn(store, f"fragments/{fid}/rgbn/front-0.h5", RGBNImage(np.full((h, w, 3), 0.5), mask, dpi))
    db_path = tmp_path / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        (p,) = db.upsert([Proposal("P1", "P2", 0.8, "m1", angle_deg=0.0, tx_mm=42.0, ty_mm=0.0)])
    data = ReviewData(db_path, store)
    for view in ("pair-colour", "pair-relief"):
        img = cv2.imdecode(np.frombuffer(data.picture(p.id, view, max_side_px=640), np.uint8), cv2.IMREAD_GRAYSCALE)
        piece = img > 100   # the fragments (grey 188) on the dark background
        cols = np.flatnonzero(piece.any(axis=0))
        split = cols[np.argmax(np.diff(cols))] + 1   # the gap between the two
        tall_a = np.count_nonzero(piece[:, :split].any(axis=1))
        tall_b = np.count_nonzero(piece[:, split:].any(axis=1))
        assert tall_a / tall_b == pytest.approx(105 / 149, abs=0.02), view
        wide_a, wide_b = np.count_nonzero(piece[:, :split].any(axis=0)), np.count_nonzero(piece[:, split:].any(axis=0))
        assert wide_a == pytest.approx(wide_b, abs=2), view   # both 40 mm wide


def test_relief_of_a_flat_fragment_is_uniform_and_colour_only_falls_back_to_grey():
    h, w = 30, 30
    n = np.dstack([np.zeros((h, w)), np.zeros((h, w)), np.ones((h, w))])
    mask = np.ones((h, w), bool)
    out = relief_picture(RGBNImage(np.full((h, w, 3), 0.3), mask, 200, normals=n))
    assert out.shape == (h, w, 3) and np.ptp(out[5:-5, 5:-5]) <= 2
    grey = relief_picture(RGBNImage(np.full((h, w, 3), 0.3), mask, 200))
    assert np.all(grey == grey[0, 0]) and grey[0, 0, 0] == grey[0, 0, 1]


def test_shrunk_rgbn_keeps_physical_size_and_unit_normals():
    from common.web.review import shrink_rgbn

    h, w = 200, 100
    n = np.dstack([np.full((h, w), 0.6), np.zeros((h, w)), np.full((h, w), 0.8)])
    img = RGBNImage(np.full((h, w, 3), 0.4), np.ones((h, w), bool), 400, normals=n)
    small = shrink_rgbn(img, 50)
    assert small.mask.shape == (50, 25)
    assert small.pixel_mm * 50 == pytest.approx(img.pixel_mm * 200)   # same physical height
    np.testing.assert_allclose(np.linalg.norm(small.normals, axis=2), 1.0, atol=1e-5)
    np.testing.assert_allclose(small.normals[10, 10], [0.6, 0, 0.8], atol=1e-5)
    assert shrink_rgbn(img, 500) is img
