"""The proposal store keeps proposals, verdicts and models across restarts and answers queries."""

import sqlite3

import pytest

from common.matching.proposals import Proposal, ProposalStore, ordered_pair


def make(a, b, p, version="0001-x"):
    a, b = ordered_pair(a, b)
    return Proposal(a, b, p, version, patch_a=1, patch_b=2, angle_deg=10.0, tx_mm=1.0, ty_mm=-2.0,
                    evidence={"columns": ["c"], "rows": [[0.5]]})


def test_ranked_list_per_fragment_is_most_probable_first_and_survives_reopen(tmp_path):
    db = tmp_path / "p.sqlite"
    with ProposalStore(db) as s:
        s.upsert([make("F1", "F2", 0.3), make("F3", "F1", 0.9), make("F1", "F4", 0.6), make("F2", "F3", 0.99)])
    with ProposalStore(db) as s:
        ranked = s.ranked("F1")
        assert [p.other("F1") for p in ranked] == ["F3", "F4", "F2"]
        assert [round(p.probability, 2) for p in ranked] == [0.9, 0.6, 0.3]
        assert ranked[0].evidence == {"columns": ["c"], "rows": [[0.5]]}
        assert [(p.fragment_a, p.fragment_b) for p in s.pending()] == [("F2", "F3"), ("F1", "F3"), ("F1", "F4"), ("F1", "F2")]


def test_verdict_sets_status_keeps_history_and_ignores_redelivery(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("A", "B", 0.8), make("A", "C", 0.7)])
        assert s.record_verdict("B", "A", "rejected", by="conservator", message_uid="u1") is not None
        assert s.record_verdict("B", "A", "rejected", by="conservator", message_uid="u1") is None  # re-delivered
        s.record_verdict("A", "B", "confirmed", by="conservator", message_uid="u2")
        assert s.get("A", "B").status == "confirmed"
        assert [v.verdict for v in s.verdicts("A")] == ["rejected", "confirmed"]
        assert s.latest_verdicts() == {("A", "B"): "confirmed"}
        assert [p.fragment_b for p in s.pending()] == ["C"]
        # re-proposing a decided pair updates the numbers but keeps the person's decision
        s.upsert([make("A", "B", 0.1, "0002-y")])
        assert s.get("A", "B").status == "confirmed" and s.get("A", "B").model_version == "0002-y"


def test_the_latest_verdict_of_a_pair_carries_the_pose_kept_with_it(tmp_path):
    """What the review page shows a decided proposal at: its latest verdict and the pose stored with it (given in
    either order, stored as the second fragment in the first's frame)."""
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("A", "B", 0.8)])
        assert s.latest_verdict("A", "B") is None
        s.record_verdict("A", "B", "confirmed", pose={"angle_deg": 12.0, "tx_mm": 7.0, "ty_mm": -6.0}, when=1.0)
        s.record_verdict("A", "B", "confirmed", when=1.0)   # same time: the later row is the latest
        assert s.latest_verdict("B", "A").pose == {"angle_deg": 10.0, "tx_mm": 1.0, "ty_mm": -2.0}   # the proposal's
        s.record_verdict("B", "A", "rejected", pose={"angle_deg": 0.0, "tx_mm": 5.0, "ty_mm": 0.0}, when=2.0)
        latest = s.latest_verdict("A", "B")
        assert latest.verdict == "rejected" and latest.pose == pytest.approx({"angle_deg": 0.0, "tx_mm": -5.0, "ty_mm": 0.0})


def test_rerank_updates_probabilities_in_one_transaction(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        ps = s.upsert([make("A", "B", 0.8), make("A", "C", 0.7)])
        s.set_probabilities([(ps[0].id, 0.1), (ps[1].id, 0.95)], "0002-z")
        assert [p.other("A") for p in s.ranked("A")] == ["C", "B"]
        assert {p.model_version for p in s.all()} == {"0002-z"}


def test_models_and_fragments_are_recorded(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        assert s.current_model() is None
        art = {"path": "models/matcher/0001-a.h5", "sha256": "ab" * 32, "bytes": 10}
        s.add_model("0001-a", art, n_train=5)
        assert s.current_model()["artifact"] == art
        assert s.add_fragment("F1", "front", art) is True
        assert s.add_fragment("F1", "front", art) is False
        assert [f["fragment"] for f in s.fragments()] == ["F1"]


def test_database_is_plain_sqlite_readable_without_tessera(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("A", "B", 0.5)])
    con = sqlite3.connect(tmp_path / "p.sqlite")
    assert con.execute("SELECT fragment_a, fragment_b, status FROM proposals").fetchall() == [("A", "B", "pending")]


def test_bad_verdict_and_self_pair_are_refused(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        with pytest.raises(ValueError, match="verdict"):
            s.record_verdict("A", "B", "maybe")
        with pytest.raises(ValueError, match="itself"):
            ordered_pair("A", "A")


def test_confirmed_pair_keeps_the_pose_the_person_saw(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("A", "B", 0.8)])
        v = s.record_verdict("A", "B", "confirmed", by="conservator", message_uid="u1")
        assert v.pose == {"angle_deg": 10.0, "tx_mm": 1.0, "ty_mm": -2.0}
        # a later re-proposal moves the proposal's pose, not the verdict's
        moved = make("A", "B", 0.9, "0002-y")
        moved.angle_deg = 45.0
        s.upsert([moved])
        assert s.get("A", "B").angle_deg == 45.0
        assert s.verdicts("A")[0].pose["angle_deg"] == 10.0
        # a verdict on a pair never proposed has no pose
        assert s.record_verdict("A", "Z", "rejected", message_uid="u2").pose is None


def test_a_pose_the_person_set_is_kept_instead_of_the_proposals(tmp_path):
    from common.matching.pose import inverse_pose

    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("A", "B", 0.8)])
        set_pose = {"angle_deg": 12.5, "tx_mm": 3.0, "ty_mm": -1.0}
        assert s.record_verdict("A", "B", "confirmed", message_uid="u1", pose=set_pose).pose == set_pose
        assert s.verdicts("A")[-1].pose == set_pose
        assert s.get("A", "B").angle_deg == 10.0   # the proposal keeps the matcher's pose
        # given from B's side (A in B's frame), it is stored as B in A's frame
        v = s.record_verdict("B", "A", "confirmed", message_uid="u2", pose=set_pose)
        assert tuple(v.pose.values()) == pytest.approx(inverse_pose(12.5, 3.0, -1.0))
        with pytest.raises(ValueError, match="tx_mm"):
            s.record_verdict("A", "B", "confirmed", pose={"angle_deg": 1.0, "tx_mm": float("nan"), "ty_mm": 0.0})


def test_database_from_before_verdict_poses_opens_and_gains_the_column(tmp_path):
    db = tmp_path / "old.sqlite"
    with ProposalStore(db) as s:
        s.upsert([make("A", "B", 0.8)])
        s.record_verdict("A", "B", "confirmed", message_uid="u1")
    con = sqlite3.connect(db)   # make it look like an old database: no pose column
    con.execute("ALTER TABLE verdicts DROP COLUMN pose")
    con.commit()
    con.close()
    with ProposalStore(db) as s:
        assert s.verdicts()[0].pose is None
        assert s.record_verdict("A", "B", "rejected", message_uid="u2").pose["tx_mm"] == 1.0


def test_proposals_are_ordered_by_mutual_proximity_then_probability(tmp_path):
    # probabilities from different queries are not comparable; the mutual proximity of both
    # fragments' rankings is, so it orders a fragment's list and the queue (pairs without one last)
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.upsert([make("F1", "F2", 0.3), make("F1", "F3", 0.99), make("F1", "F4", 0.6), make("F1", "F5", 0.95)])
        assert s.set_mutual([("F2", "F1", 0.9), ("F1", "F3", 0.2), ("F1", "F4", 0.5), ("F1", "F9", 0.7)]) == 3
        assert [p.other("F1") for p in s.ranked("F1")] == ["F2", "F4", "F3", "F5"]
        assert [p.other("F1") for p in s.pending()] == ["F2", "F4", "F3", "F5"]
        assert s.get("F1", "F2").mutual == 0.9 and s.get("F1", "F5").mutual is None
        # an upsert without a mutual proximity keeps the stored one; one with it replaces it
        s.upsert([make("F1", "F2", 0.4)])
        assert s.get("F1", "F2").mutual == 0.9
        p = make("F1", "F2", 0.4)
        p.mutual = 0.1
        s.upsert([p])
        assert s.get("F1", "F2").mutual == 0.1
        assert s.get("F1", "F2").to_event_fields()["mutual"] == 0.1


def test_database_from_before_mutual_proximity_opens_and_gains_the_column(tmp_path):
    db = tmp_path / "old.sqlite"
    with ProposalStore(db) as s:
        s.upsert([make("A", "B", 0.8), make("A", "C", 0.9)])
    con = sqlite3.connect(db)   # make it look like an old database: no mutual column
    con.execute("DROP INDEX proposals_status_mutual")
    con.execute("ALTER TABLE proposals DROP COLUMN mutual")
    con.commit()
    con.close()
    with ProposalStore(db) as s:
        assert [p.mutual for p in s.ranked("A")] == [None, None]
        assert [p.other("A") for p in s.ranked("A")] == ["C", "B"]   # by probability until known
        s.set_mutual([("A", "B", 0.5)])
        assert [p.other("A") for p in s.ranked("A")] == ["B", "C"]


def _docking(a="A", b="B", **kw):
    from common.matching.proposals import StoredDocking

    nan = float("nan")
    d = dict(best=(12.5, 1.25, -3.0, 40.0, 22.5, 0.0), paint=True, paint_mm=nan,
             pose=(190.0, 0.1, 0.2, 38.0, 20.0, nan), alternatives=[(10.0, 1.0, 2.0, 30.0, 15.0, 1.5)])
    d.update(kw)
    return StoredDocking(a, b, "in-a", "in-b", "docking-1/test", **d)


def test_a_stored_docking_comes_back_for_its_inputs_and_version_only(tmp_path):
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.put_docking(_docking())
    with ProposalStore(tmp_path / "p.sqlite") as s:
        back = s.docking("A", "B", "in-a", "in-b", "docking-1/test")
        assert back.best == (12.5, 1.25, -3.0, 40.0, 22.5, 0.0) and back.alternatives == [(10.0, 1.0, 2.0, 30.0, 15.0, 1.5)]
        assert back.paint and back.paint_mm != back.paint_mm                  # NaN kept (as NULL)
        assert back.pose[:5] == (190.0, 0.1, 0.2, 38.0, 20.0) and back.pose[5] != back.pose[5]
        assert s.docking("A", "B", "in-a", "other", "docking-1/test") is None
        assert s.docking("A", "B", "in-a", "in-b", "docking-2/test") is None
        with pytest.raises(ValueError):
            s.docking("B", "A", "in-b", "in-a", "docking-1/test")          # stored order only
        s.put_docking(_docking(paint=False, pose=None, alternatives=[]))       # the pair's one row, replaced
        assert s.count_dockings() == 1 and not s.docking("A", "B", "in-a", "in-b", "docking-1/test").paint


def test_a_fragments_docking_hubness_comes_back_for_its_inputs_and_version_only(tmp_path):
    """The last value stored for a fragment is read by any worker, for the fragment's current docking
    inputs and this docking version only; more fragments than one SQLite statement may name come back."""
    with ProposalStore(tmp_path / "p.sqlite") as s:
        s.put_dock_hubness("A", "in-a", "docking-1/test", 31.5, "0002-x")
        s.put_dock_hubness("B", "in-b", "docking-1/test", 12.0)
        s.put_dock_hubness("A", "in-a", "docking-1/test", 33.25, "0003-y")          # replaced: the last stays
    with ProposalStore(tmp_path / "p.sqlite") as s:
        assert s.dock_hubness({"A": "in-a", "B": "in-b", "C": "in-c"}, "docking-1/test") == {"A": 33.25, "B": 12.0}
        assert s.dock_hubness({"A": "in-a", "B": "re-extracted"}, "docking-1/test") == {"A": 33.25}
        assert s.dock_hubness({"A": "in-a"}, "docking-2/test") == {}
        many = {f"F{k:04d}": f"in-{k}" for k in range(1203)}
        for k, (f, i) in enumerate(many.items()):
            if k % 100 == 7 or k == 1202:
                s.put_dock_hubness(f, i, "docking-1/test", float(k))
        assert s.dock_hubness(many, "docking-1/test") == {f"F{k:04d}": float(k) for k in range(1203)
                                                           if k % 100 == 7 or k == 1202}


def test_two_workers_storing_the_same_pairs_docking_do_not_fail(tmp_path):
    """Two matcher workers that docked one pair at once both store it (each in its own connection, as two
    processes would): neither fails on the other's lock or row, and the pair has one row."""
    import threading

    errors = []

    def worker():
        try:
            with ProposalStore(tmp_path / "p.sqlite") as s:
                for k in range(40):
                    s.put_docking(_docking())
                    s.put_docking(_docking("A", f"C{k}"))
        except Exception as exc:   # noqa: BLE001 - collected for the assertion
            errors.append(exc)

    ProposalStore(tmp_path / "p.sqlite").close()
    threads = [threading.Thread(target=worker) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    with ProposalStore(tmp_path / "p.sqlite") as s:
        assert s.count_dockings() == 41
        assert s.docking("A", "B", "in-a", "in-b", "docking-1/test").best[0] == 12.5
