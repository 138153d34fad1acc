"""The matcher service proposes joins for new fragments and learns from verdicts."""

import logging

import numpy as np
import pytest

from common.bus.worker import StageContext
from common.features import save_features
from common.matching.models import load_model, save_model
from common.matching.online import train_model
from common.matching.pairs import training_set
from common.matching.proposals import ProposalStore
from common.messages import new_message, validate
from common.store import Store


@pytest.fixture
def station(tmp_path, small_wall):
    wall, tables, cues, poses = small_wall
    store = Store(tmp_path / "root")
    model, _ = train_model(training_set(cues, poses, wall.adjacency, seed=1))
    ref = save_model(store, model)
    db = ProposalStore(tmp_path / "root" / "matches" / "proposals.sqlite")
    db.add_model(model.version, ref.to_dict(), n_train=len(model.training[1]))
    arts = {fid: save_features(store, f"fragments/{fid}/features/front-test.h5", t) for fid, t in tables.items()}
    ctx = StageContext(store=store, config={"top": 5, "check": 2}, log=logging.getLogger("test.matcher"),
                       progress=lambda f, t: None, service="matcher")
    return wall, store, db, arts, ctx


def _n_patches(store, art):
    from common.features import load_features
    return int((load_features(store, art).patch_kind == "p10").sum())


def test_features_ready_proposes_ranked_joins_and_stores_them(station):
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    ids = [f.id for f in wall.fragments[:20]]
    # end with a fragment that has patches of its own (a crumb has none and gets no proposals)
    ids.sort(key=lambda i: _n_patches(store, arts[i]) >= 5)
    events = []
    for fid in ids:
        events += matcher.handle(new_message("features.ready", fragment=fid, face="front", artifact=arts[fid]), ctx)
    assert events and all(validate(e)["type"] == "match.proposed" for e in events)
    last = [e for e in events if ids[-1] in (e["fragment"], e["other"])]
    assert 1 <= len(last) <= 5
    ranked = db.ranked(ids[-1])
    # a fragment's proposals come from several queries: ordered by their mutual proximity, which
    # every stored pair has, in [0, 1)
    assert all(p.mutual is not None and 0.0 <= p.mutual < 1.0 for p in db.all())
    assert [p.mutual for p in ranked] == sorted((p.mutual for p in ranked), reverse=True)
    # the last fragment's best partners were ranked again, so their rankings know it, and its
    # proposals' mutual proximity is the closed form of its rank in both rankings
    st = matcher._state(ctx)
    mine = st.index.rankings[ids[-1]]
    for p in ranked[:3]:
        other = p.other(ids[-1])
        theirs = st.index.rankings[other]
        assert ids[-1] in theirs
        x = (mine.index(other) + 1) / len(mine) * (theirs.index(ids[-1]) + 1) / len(theirs)
        assert p.mutual == pytest.approx(1 - x * (1 - np.log(x)), abs=1e-9)
    assert db.count() >= len(ids)
    # the best proposals were aligned: their pose maps B onto A without overlap
    aligned = [p for p in db.all() if p.alignment]
    assert aligned and all(p.alignment["overlap_mm2"] < 50 for p in aligned[:5])
    # a re-delivered job is harmless: same proposals, same probabilities
    before = {(p.fragment_a, p.fragment_b): p.probability for p in db.all()}
    matcher.handle(new_message("features.ready", fragment=ids[-1], face="front", artifact=arts[ids[-1]]), ctx)
    assert {(p.fragment_a, p.fragment_b): p.probability for p in db.all()} == before


def _arrive(station, n: int) -> None:
    """The wall's first ``n`` fragments' features arrive at the matcher, one job each."""
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    for f in wall.fragments[:n]:
        matcher.handle(new_message("features.ready", fragment=f.id, face="front", artifact=arts[f.id]), ctx)


def test_verdict_refits_a_new_model_version_and_is_idempotent(station):
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    _arrive(station, 15)
    before = db.current_model()["version"]
    top = db.pending(1)[0]
    truth = wall.is_neighbour(top.fragment_a, top.fragment_b)
    msg = new_message("match.verified", fragment=top.fragment_a, other=top.fragment_b,
                      verdict="confirmed" if truth else "rejected", by="test")
    (refitted,) = [validate(e) for e in matcher.handle(msg, ctx)]   # the full re-rank follows as its own job
    after = db.current_model()
    assert refitted["type"] == "match.refitted" and refitted["model_version"] == after["version"]
    assert refitted["previous"] == before and refitted["verdicts"] == 1
    assert after["version"] != before and int(after["version"][:4]) == int(before[:4]) + 1
    model = load_model(store, after["artifact"])
    assert model.info["verdict_rows"] > 0
    assert db.get(top.fragment_a, top.fragment_b).status == ("confirmed" if truth else "rejected")
    assert {p.model_version for p in db.pending(10 ** 6)} == {after["version"]}
    assert matcher.handle(msg, ctx) == []   # re-delivered: no second verdict, no new model
    assert len(db.verdicts()) == 1 and db.current_model()["version"] == after["version"]
    # a verdict with the pose the person set (other in fragment's frame, here given from B's side)
    # keeps that pose, stored as B in A's frame, for the reconstruction
    from common.matching.pose import inverse_pose

    set_pose = {"angle_deg": 33.0, "tx_mm": 20.0, "ty_mm": -7.5}
    matcher.handle(new_message("match.verified", fragment=top.fragment_b, other=top.fragment_a,
                               verdict="confirmed", pose=set_pose), ctx)
    stored = db.verdicts()[-1].pose
    assert tuple(stored.values()) == pytest.approx(inverse_pose(33.0, 20.0, -7.5))


def test_a_verdict_whose_job_was_stopped_is_learned_when_it_is_delivered_again(station):
    # the verdict job records the verdict first; a worker killed after that but before the model is saved (or
    # before the pending proposals are re-scored) left the verdict unlearned: the re-delivery said "already
    # recorded" and did nothing, until the next verdict
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    _arrive(station, 12)
    before = db.current_model()["version"]
    top = db.pending(1)[0]
    msg = new_message("match.verified", fragment=top.fragment_a, other=top.fragment_b, verdict="rejected", by="test")
    # the stopped job got as far as recording it
    assert db.record_verdict(top.fragment_a, top.fragment_b, "rejected", by="test", message_uid=msg["uid"]) is not None
    (refitted,) = [validate(e) for e in matcher.handle(msg, ctx)]
    after = db.current_model()["version"]
    assert refitted["type"] == "match.refitted" and after != before and refitted["model_version"] == after
    assert len(db.verdicts()) == 1 and {p.model_version for p in db.pending(10 ** 6)} == {after}
    assert load_model(store, db.current_model()["artifact"]).info["verdicts_key"] == matcher.verdicts_key(
        db.latest_verdicts())
    # stopped after the model was made current, before every pending proposal was re-scored under it
    stale = db.pending(1)[0]
    db.set_probabilities([(stale.id, stale.probability)], before)
    (again,) = [validate(e) for e in matcher.handle(msg, ctx)]
    assert again["type"] == "match.refitted" and again["model_version"] == after
    assert db.current_model()["version"] == after and {p.model_version for p in db.pending(10 ** 6)} == {after}
    # and once it is all done, a re-delivery does nothing
    assert matcher.handle(msg, ctx) == [] and db.current_model()["version"] == after


def test_rejections_lower_the_probability_of_similar_pairs(station):
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    _arrive(station, 12)
    wrong = [p for p in db.pending(50) if not wall.is_neighbour(p.fragment_a, p.fragment_b)][:4]
    assert wrong
    before = {(p.fragment_a, p.fragment_b): p.probability for p in wrong}
    for p in wrong:
        matcher.handle(new_message("match.verified", fragment=p.fragment_a, other=p.fragment_b,
                                   verdict="rejected"), ctx)
    model = load_model(store, db.current_model()["artifact"])
    for (a, b), p0 in before.items():
        ev = db.get(a, b).evidence
        rows = np.array(ev["rows"], dtype=float)
        assert model.probability(rows).mean() < p0


def test_unknown_job_type_is_refused(station):
    import services.matcher as matcher
    *_, ctx = station
    from common.messages import MessageError
    with pytest.raises(MessageError, match="matcher handles"):
        matcher.handle(new_message("rgbn.ready", fragment="F", face="front",
                                   artifact={"path": "x", "sha256": "0" * 64, "bytes": 1}), ctx)


def test_a_docking_model_answers_from_the_fast_stages_then_docks_in_a_job_of_its_own(station):
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    model = load_model(store, db.current_model()["artifact"])
    model.docking = (0.15, -4.0)            # a docking stage (its calibration's values do not matter here)
    model.version = "0002-docking"
    db.add_model(model.version, save_model(store, model).to_dict(), n_train=len(model.training[1]))
    ids = [f.id for f in wall.fragments[:14]]
    ids.sort(key=lambda i: _n_patches(store, arts[i]) >= 5)
    for fid in ids[:-1]:
        matcher.handle(new_message("features.ready", fragment=fid, face="front", artifact=arts[fid]), ctx)
    first = matcher.handle(new_message("features.ready", fragment=ids[-1], face="front", artifact=arts[ids[-1]]), ctx)
    proposed = [validate(e) for e in first if e["type"] == "match.proposed"]
    (ranked,) = [validate(e) for e in first if e["type"] == "match.ranked"]
    assert proposed and all(e["stage"] == "ranked" and "pose" not in e for e in proposed)
    assert ranked["fragment"] == ids[-1] and ranked["artifact"] == arts[ids[-1]].to_dict()
    others = {e["other"] if e["fragment"] == ids[-1] else e["fragment"] for e in proposed}
    assert set(ranked["proposed"]) == others

    docked = [validate(e) for e in matcher.handle(ranked, ctx)]
    assert docked and all(e["type"] == "match.proposed" and e["stage"] == "docked" for e in docked)
    assert any("pose" in e and e["alignment"]["contact_mm"] >= 0 for e in docked)
    # every join of the first answer is answered again, and the store holds the docked answer
    assert others <= {e["other"] if e["fragment"] == ids[-1] else e["fragment"] for e in docked}
    for e in docked:
        assert db.get(e["fragment"], e["other"]).probability == pytest.approx(e["probability"])
    # a match.ranked for features that were replaced since is skipped (the new ones bring their own)
    stale = dict(ranked, artifact=dict(ranked["artifact"], sha256="0" * 64))
    assert matcher.handle(stale, ctx) == []


def _arrivals_under_a_docking_model(station, n: int):
    """A docking model made current (version 0002-docking), then the first ``n`` fragments arrive: each
    one's first answer and its docking job. Returns that model."""
    import services.matcher as matcher

    wall, store, db, arts, ctx = station
    model = load_model(store, db.current_model()["artifact"])
    model.docking = (0.15, -4.0)
    model.version = "0002-docking"
    db.add_model(model.version, save_model(store, model).to_dict(), n_train=len(model.training[1]))
    for f in wall.fragments[:n]:
        for e in matcher.handle(new_message("features.ready", fragment=f.id, face="front", artifact=arts[f.id]), ctx):
            if e["type"] == "match.ranked":
                matcher.handle(e, ctx)
    return model


def test_a_model_update_ranks_every_fragment_again_and_leaves_new_dockings_to_jobs_of_their_own(station):
    """match.verified → match.refitted: that job ranks every fragment under the new model with the dockings
    made before (none new), updates every stored pair's mutual proximity, and lists in match.reranked events,
    a few per job, each fragment whose best hold a pair never docked or whose top joins are not all stored;
    those jobs dock and propose them again. A match.refitted or match.reranked of a model no longer current
    is skipped."""
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    ctx.config["redock_batch"] = 3
    model = _arrivals_under_a_docking_model(station, 24)
    wrong = [p for p in db.pending(50) if not wall.is_neighbour(p.fragment_a, p.fragment_b)][:3]
    events = []
    for p in wrong:
        events = matcher.handle(new_message("match.verified", fragment=p.fragment_a, other=p.fragment_b,
                                            verdict="rejected"), ctx)
    (refitted,) = events
    st = matcher._state(ctx)
    docked = set(st.index._dockings)
    follow = [validate(e) for e in matcher.handle(refitted, ctx)]
    assert set(st.index._dockings) == docked                         # the re-rank docked nothing
    version = db.current_model()["version"]
    assert refitted["model_version"] == version
    assert all(v == version for v, _ in st.index.hubness.values())
    assert follow and all(e["type"] == "match.reranked" and e["model_version"] == version for e in follow)
    redock = [f for e in follow for f in e["redock"]]
    assert all(1 <= len(e["redock"]) <= 3 for e in follow) and len(set(redock)) == len(redock)
    for f in redock:   # each has pairs to dock or joins to store
        stored = {p.other(f) for p in db.ranked(f, limit=10 ** 6)}
        head = st.index.rankings[f][:12]
        assert set(st.index.rankings[f][:5]) - stored or any(tuple(sorted((f, o))) not in docked for o in head)
    # every stored pair's mutual proximity is that of the new rankings
    for p in db.all():
        assert p.mutual == pytest.approx(st.index.mutual(p.fragment_a, [p.fragment_b])[0], abs=1e-9)
    for e in follow:
        proposed = [validate(d) for d in matcher.handle(e, ctx)]
        assert all(d["type"] == "match.proposed" and d["stage"] == "docked" for d in proposed)
    assert len(st.index._dockings) > len(docked)
    for f in redock:   # every fragment's top joins are stored now, docked
        stored = {p.other(f) for p in db.ranked(f, limit=10 ** 6)}
        assert set(st.index.rankings[f][:5]) <= stored
    assert matcher.handle(dict(refitted, model_version=model.version), ctx) == []
    assert matcher.handle(dict(follow[0], model_version=model.version), ctx) == []


def test_a_join_stored_without_a_pose_gets_one_when_a_model_update_lifts_it(station):
    """Seen on 16 real RePAIR fragments: a join stored below a fragment's docked best has no pose; a verdict's
    refit lifted it to the top of the queue (99 %), but the re-rank found nothing to dock (the pair had been
    docked from its other side) and nothing missing, so it stayed without a pose and the review page could not
    show it joined. A fragment whose best hold such a join is proposed again, and the join takes the pair's
    docked pose (here: the pose it had, which the store had lost)."""
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    _arrivals_under_a_docking_model(station, 24)
    wrong = next(p for p in db.pending(50) if not wall.is_neighbour(p.fragment_a, p.fragment_b))
    (refitted,) = matcher.handle(new_message("match.verified", fragment=wrong.fragment_a, other=wrong.fragment_b,
                                             verdict="rejected"), ctx)
    for e in matcher.handle(refitted, ctx):                   # the update's re-rank, done
        matcher.handle(e, ctx)
    st = matcher._state(ctx)
    target = next(p for p in db.pending(10 ** 6) if p.angle_deg is not None
                  and p.fragment_b in st.index.rankings.get(p.fragment_a, [])[:5])
    pose = (target.angle_deg, target.tx_mm, target.ty_mm)
    db._db.execute("UPDATE proposals SET angle_deg = NULL, tx_mm = NULL, ty_mm = NULL, alignment = NULL "
                   "WHERE id = ?", (target.id,))              # stored without a pose
    follow = matcher.handle(refitted, ctx)                    # the same model ranks alike: nothing else to do
    redock = {f for e in follow for f in e["redock"]}
    assert target.fragment_a in redock
    for e in follow:
        matcher.handle(e, ctx)
    again = db.get(target.fragment_a, target.fragment_b)
    assert again.alignment is not None
    assert (again.angle_deg, again.tx_mm, again.ty_mm) == pytest.approx(pose, abs=1e-6)


def test_a_join_below_the_docked_best_carries_the_pose_of_a_docking_made_before(station):
    """Stage 3 docks a fragment's best few; a kept join below them whose pair was docked before (from the other
    side, or by an earlier ranking) now carries that docking's pose and alternatives instead of none."""
    import services.matcher as matcher
    from common.matching.pose import wrapped_deg   # a proposal's angle is in [-180, 180), the docking's in [0, 360)

    wall, store, db, arts, ctx = station
    model = _arrivals_under_a_docking_model(station, 24)
    st = matcher._state(ctx)
    f = wall.fragments[0].id
    found = st.index.propose(st.index.cues[f], model, top=8, check=0, dock_candidates=1)
    below = [c for c in found[1:] if st.index.docked(f, c.other)]
    assert below, "some pairs below the best were docked before"
    for c in below:
        q = st.index.pose(f, c.other)
        assert c.alignment is not None and (c.alignment.angle_deg, c.alignment.tx_mm) == (wrapped_deg(q.angle_deg), q.tx_mm)
        assert np.isnan(c.alignment.score) and len(c.alignment.alternatives) == len(st.index.alternatives(f, c.other))
    assert all(c.alignment is None for c in found[1:] if not st.index.docked(f, c.other))


def test_a_restarted_matcher_worker_docks_no_pair_docked_before(station, monkeypatch):
    """The dockings are kept in the proposal store: a matcher worker restarted after the arrivals (its
    caches gone) re-ranks after a model update docking nothing, sends on to be docked again the fragments
    the worker before it did, not all, and their jobs dock only pairs never docked — each pair once."""
    import common.matching.index as index_mod
    import services.matcher as matcher

    wall, store, db, arts, ctx = station
    _arrivals_under_a_docking_model(station, 20)
    ids = [f.id for f in wall.fragments[:20]]
    wrong = [p for p in db.pending(50) if not wall.is_neighbour(p.fragment_a, p.fragment_b)][0]
    (refitted,) = matcher.handle(new_message("match.verified", fragment=wrong.fragment_a, other=wrong.fragment_b,
                                             verdict="rejected"), ctx)
    kept = db.count_dockings()
    assert kept == len(matcher._state(ctx).index._dockings) > 0
    before = [f for e in matcher.handle(refitted, ctx) for f in e["redock"]]

    calls, dock = [], index_mod.dock_frames
    monkeypatch.setattr(index_mod, "dock_frames", lambda *a, **kw: calls.append(1) or dock(*a, **kw))
    matcher._STATES.clear()                                     # the worker restarted
    follow = [validate(e) for e in matcher.handle(refitted, ctx)]
    assert calls == []                                          # the re-rank docked nothing
    st = matcher._state(ctx)
    assert st.index is not None and len(st.index) == len(ids)
    after = [f for e in follow for f in e["redock"]]
    # not every fragment sent to be docked again (as before the dockings were kept), but exactly those the
    # worker that stayed sent: the full re-rank depends on the fragments, the model and the dockings only
    assert after == before and len(after) < len(ids)
    for e in follow:
        matcher.handle(e, ctx)
    assert len(calls) == db.count_dockings() - kept             # only pairs never docked, each once


def test_a_redock_batch_the_messages_cannot_carry_is_refused_by_name():
    """``match.reranked`` carries at most 64 fragments (docs/messages.md): a larger ``redock_batch`` made
    every full re-rank's events invalid, and the worker parked each job as if its input were bad."""
    import pytest

    from common.messages import MAX_REDOCK_FRAGMENTS
    from services.matcher import REDOCK_BATCH, redock_batch

    assert redock_batch({}) == REDOCK_BATCH and redock_batch({"redock_batch": MAX_REDOCK_FRAGMENTS}) == 64
    for bad in (0, MAX_REDOCK_FRAGMENTS + 1, "8", True, 2.5):
        with pytest.raises(ValueError, match=r"\[services.matcher\] redock_batch must be an integer from 1 to 64"):
            redock_batch({"redock_batch": bad})


def test_a_job_that_proposes_nothing_names_its_fragment_in_the_log(station, caplog):
    """A fragment with no partner to propose (the first one in the index) was logged as ``fragment -: 0
    proposals``: the log names it, for its features.ready and for a re-rank's match.reranked job alike."""
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    fid = wall.fragments[0].id
    with caplog.at_level(logging.INFO, logger="test.matcher"):
        assert matcher.handle(new_message("features.ready", fragment=fid, face="front", artifact=arts[fid]), ctx) == []
        version = matcher._state(ctx).model.version
        assert matcher.handle(new_message("match.reranked", model_version=version, redock=[fid]), ctx) == []
    lines = [r.getMessage() for r in caplog.records if "proposals" in r.getMessage()]
    assert len(lines) == 2 and all(line.startswith(f"fragment {fid}: 0 proposals") for line in lines), lines
    assert "fragment -" not in caplog.text
    # with no proposal there is no best: the line says why instead of "(best nan)"
    assert all(line.endswith("(no other fragment indexed yet)") and "nan" not in line for line in lines), lines


@pytest.mark.parametrize("indexed, why", [(3, "none of the 3 other fragments could be scored with it"),
                                           (1, "the 1 other fragment could not be scored with it")])
def test_a_fragment_no_pair_could_be_scored_for_says_so_in_the_log(station, caplog, indexed, why):
    """A crumb (no valid patch) among indexed fragments gets no proposal; its log line said "(best nan)", and
    "1 other fragments" with one."""
    import dataclasses

    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    from common.features import load_features
    ids = [f.id for f in wall.fragments[:indexed + 1]]
    for fid in ids[:indexed]:
        matcher.handle(new_message("features.ready", fragment=fid, face="front", artifact=arts[fid]), ctx)
    table = load_features(store, arts[ids[indexed]])
    crumb = dataclasses.replace(table, patch_coverage=np.zeros_like(table.patch_coverage))   # no patch is valid
    art = save_features(store, f"fragments/{ids[indexed]}/features/front-crumb.h5", crumb)
    with caplog.at_level(logging.INFO, logger="test.matcher"):
        assert matcher.handle(new_message("features.ready", fragment=ids[indexed], face="front", artifact=art),
                              ctx) == []
    (line,) = [r.getMessage() for r in caplog.records if "proposals" in r.getMessage()]
    assert line.startswith(f"fragment {ids[indexed]}: 0 proposals, ") and "nan" not in line
    assert line.endswith(f"({why})"), line


def test_one_proposal_is_logged_in_the_singular(station, caplog):
    import services.matcher as matcher
    wall, store, db, arts, ctx = station
    first, second = (f.id for f in wall.fragments[:2])
    matcher.handle(new_message("features.ready", fragment=first, face="front", artifact=arts[first]), ctx)
    with caplog.at_level(logging.INFO, logger="test.matcher"):
        matcher.handle(new_message("features.ready", fragment=second, face="front", artifact=arts[second]), ctx)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith(f"fragment {second}: ")]
    assert lines and all(line.startswith(f"fragment {second}: 1 proposal, ") for line in lines), lines


@pytest.mark.parametrize("damage", ["corrupt", "not-features"])
def test_a_bad_feature_artifact_rejects_its_own_job_only_and_is_never_recorded(station, damage):
    """docs/storage.md: a corrupt input is refused (input.rejected) for its job. The matcher recorded the features
    in its proposal store before reading them, so every later job (each reads every recorded table) failed on that
    one file too, and a fragment's good features were replaced by the bad ones; now a table is read before it is
    recorded."""
    import services.matcher as matcher
    from common.store import ArtifactError

    wall, store, db, arts, ctx = station
    a, b, c = (f.id for f in wall.fragments[:3])
    _arrive(station, 2)
    good = db.fragments(face="front")
    if damage == "corrupt":   # the digest the message states is not the file's
        bad = dict(arts[c].to_dict(), sha256="0" * 64)
    else:                     # a valid artifact of another schema
        bad = store.write(f"fragments/{c}/features/front-bogus.h5", "tessera.noop", 1,
                          lambda f: f.create_dataset("received", data=1.0)).to_dict()
    for fid in (c, a):        # a new fragment, and one whose good features are recorded
        with pytest.raises(ArtifactError):
            matcher.handle(new_message("features.ready", fragment=fid, face="front", artifact=bad), ctx)
    assert db.fragments(face="front") == good, "nothing of the bad artifact recorded"
    matcher._STATES.clear()   # a restarted worker reads every recorded table
    events = matcher.handle(new_message("features.ready", fragment=c, face="front", artifact=arts[c]), ctx)
    assert all(e["type"] in ("match.proposed", "match.ranked") for e in events)
    assert {r["fragment"] for r in db.fragments(face="front")} == {a, b, c}


def test_a_stored_model_calibrated_for_another_ribbon_score_is_calibrated_again_on_load(station):
    """A station upgraded past a change of the ribbon's score: its current model's ribbon calibration no longer holds,
    so the matcher fits it again on its bootstrap wall and stores the result as the current model, with a note."""
    import dataclasses

    import services.matcher as matcher
    from common.matching.ribbon import RIBBON_DEFINITION

    wall, store, db, arts, ctx = station
    base = load_model(store, db.current_model()["artifact"])
    info = {k: v for k, v in base.info.items() if k != "ribbon_definition"}    # as models were stored before
    stale = dataclasses.replace(base, ribbon=(10.0, -3.0), info=info)
    stale.version = f"0002-{stale.digest()}"
    db.add_model(stale.version, save_model(store, stale).to_dict(), n_train=len(stale.training[1]))
    ctx.config["bootstrap_fragments"], ctx.config["bootstrap_seed"] = 12, 3
    matcher.handle(new_message("features.ready", fragment=wall.fragments[0].id, face="front",
                               artifact=arts[wall.fragments[0].id]), ctx)
    current = db.current_model()
    assert current["version"] != stale.version and current["version"].startswith("0003-")
    assert "ribbon calibrated again" in current["note"]
    renewed = load_model(store, current["artifact"])
    assert renewed.info["ribbon_definition"] == RIBBON_DEFINITION and renewed.ribbon != pytest.approx((10.0, -3.0))
    np.testing.assert_array_equal(renewed.coef, stale.coef)
    assert matcher._state(ctx).model.version == current["version"]


def test_a_station_set_for_one_fresco_ranks_with_an_index_of_one_fresco(tmp_path):
    """``[services.matcher] single_fresco`` reaches the index; a value that is not a TOML boolean is refused by name
    (the string "false" would otherwise read as true)."""
    import services.matcher as matcher

    def ctx(value):
        return StageContext(store=Store(tmp_path / str(value)), config={"single_fresco": value},
                            log=logging.getLogger("test.matcher"), progress=lambda f, t: None, service="matcher")

    db = ProposalStore(tmp_path / "db.sqlite")
    assert matcher._State(db, single_fresco=True).index.single_fresco
    assert not matcher._State(db).index.single_fresco
    with pytest.raises(ValueError, match="single_fresco must be true or false"):
        matcher._state(ctx("false"))


def test_a_station_sets_the_same_fresco_ratios_weight(tmp_path, monkeypatch):
    """``[services.matcher] fresco_weight`` reaches the index (unset: the library's default); a value that is not a
    number >= 0 (a string, a boolean, a negative number) is refused by name."""
    import services.matcher as matcher

    monkeypatch.setattr(matcher, "_sync", lambda st, ctx: None)   # no fragments or model to read: the index only

    def ctx(name, config):
        return StageContext(store=Store(tmp_path / name), config=config, log=logging.getLogger("test.matcher"),
                            progress=lambda f, t: None, service="matcher")

    assert matcher._state(ctx("four", {"fresco_weight": 4})).index.fresco_weight == 4.0
    assert matcher._state(ctx("unset", {})).index.fresco_weight is None
    for k, bad in enumerate(("4", True, -1.0)):
        with pytest.raises(ValueError, match=r"\[services.matcher\] fresco_weight must be a number >= 0"):
            matcher._state(ctx(f"bad{k}", {"fresco_weight": bad}))


def test_a_proposal_turned_half_round_keeps_its_angle_in_the_stated_range():
    """A proposal is stored as fragment_b in fragment_a's frame; a query sorting after its partner had its pose
    inverted, and −180° (the docking's 180°, wrapped) came out as +180°, outside the [−180°, 180°) that
    docs/messages.md states for ``match.proposed``. The inverted pose is the same rotation, wrapped."""
    from types import SimpleNamespace

    from common.matching.alignment import Alignment, pose_matrix
    from common.matching.index import Candidate
    from services.matcher import _proposal

    cues = SimpleNamespace(patch_index=np.arange(4))
    st = SimpleNamespace(index=SimpleNamespace(cues={"F2": cues, "F1": cues}), model=SimpleNamespace(version="m1"))
    al = Alignment(-180.0, 12.0, -3.0, float("nan"), 20.0, 0.0, 1.0, ((-180.0, 1.0, 2.0), (90.0, 0.0, 5.0)))
    c = Candidate("F2", "F1", 0.5, 0, 1, np.zeros((0, 2), int), np.zeros((0, 1)), alignment=al)
    p = _proposal(c, st, [])
    assert (p.fragment_a, p.fragment_b) == ("F1", "F2")
    poses = [(p.angle_deg, p.tx_mm, p.ty_mm), (p.alignment["angle_deg"], p.alignment["tx_mm"], p.alignment["ty_mm"]),
             *[(q["angle_deg"], q["tx_mm"], q["ty_mm"]) for q in p.alignment["alternatives"]]]
    assert all(-180.0 <= q[0] < 180.0 for q in poses), poses
    # each is still the inverse of the query's pose: composed with it, the identity
    for q, mine in zip([poses[0], *poses[2:]], [(-180.0, 12.0, -3.0), *al.alternatives]):
        np.testing.assert_allclose(pose_matrix(*q) @ pose_matrix(*mine), np.eye(3), atol=1e-9)
